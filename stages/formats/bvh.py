"""BVH motion files: reading (any channel order, any joint) and writing (a whole skeleton or one head joint).

BVH rotations are intrinsic Euler angles in degrees, composed in the order the channels are listed
("Zrotation Xrotation Yrotation" is R = R_Z R_X R_Y). BVH's usual axes (y up, the character facing +z, its left
towards +x) are the glTF axes of stages.geometry.rotations, so a joint's local rotation maps to a quaternion unchanged.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from msflow import UserError
from stages.geometry.rotations import euler_order_to_quat, quat_to_euler_order

POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")
ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")


@dataclass
class BvhJoint:
    name: str
    parent: int  # index into Bvh.joints, -1 for a root
    offset: np.ndarray  # (3,) rest offset from the parent
    channels: list[str]  # e.g. ["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", ...]
    channel_start: int = 0  # first column of this joint in Bvh.motion
    end_site: np.ndarray | None = None  # (3,) offset of an "End Site" child, if any

    @property
    def rotation_order(self) -> str:
        """Axes of the rotation channels in listed order, e.g. "ZXY" ("" when the joint has none)."""
        return "".join(c[0].upper() for c in self.channels if c in ROTATION_CHANNELS)


@dataclass
class Bvh:
    joints: list[BvhJoint]
    frame_time: float  # seconds per frame
    motion: np.ndarray  # (frames, total channels) float64
    source: str | None = None  # file name, for error messages
    _by_name: dict[str, int] = field(default_factory=dict, repr=False)

    def __post_init__(self):
        self._by_name = {j.name: i for i, j in enumerate(self.joints)}

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    @property
    def frames(self) -> int:
        return self.motion.shape[0]

    def joint(self, name: str, *, field: str | None = None) -> BvhJoint:
        if name not in self._by_name:
            raise UserError(
                f"BVH has no joint named {name!r}; joints: {', '.join(j.name for j in self.joints)}",
                file=self.source,
                field=field,
            )
        return self.joints[self._by_name[name]]

    def channel(self, joint: BvhJoint, channel: str) -> np.ndarray | None:
        if channel not in joint.channels:
            return None
        return self.motion[:, joint.channel_start + joint.channels.index(channel)]


class BvhSyntax:
    """The HIERARCHY section as a token stream with line numbers, for a small recursive-descent parser."""

    def __init__(self, text: str, source: str | None, first_line: int = 1):
        self.source = source
        self.tokens = [
            (token, number) for number, line in enumerate(text.splitlines(), start=first_line) for token in line.split()
        ]
        self.at = 0

    def fail(self, message: str):
        line = self.tokens[min(self.at, len(self.tokens) - 1)][1] if self.tokens else 1
        raise UserError(f"not a valid BVH file: {message} (line {line})", file=self.source)

    def peek(self) -> str | None:
        return self.tokens[self.at][0] if self.at < len(self.tokens) else None

    def take(self, what: str = "a token") -> str:
        if self.at >= len(self.tokens):
            self.fail(f"the HIERARCHY ends where {what} was expected")
        self.at += 1
        return self.tokens[self.at - 1][0]

    def expect(self, word: str, context: str) -> None:
        found = self.take(repr(word))
        if found != word:
            self.at -= 1
            self.fail(f"expected {word!r} {context}, found {found!r}")

    def numbers(self, count: int, what: str) -> list[float]:
        words = [self.take(what) for _ in range(count)]
        try:
            return [float(w) for w in words]
        except ValueError:
            self.fail(f"{what} needs {count} numbers, got {words}")


def parse_joint(syntax: BvhSyntax, joints: list[BvhJoint], parent: int, channel_count: int) -> int:
    """``ROOT|JOINT name { OFFSET x y z  CHANNELS n ...  (JOINT ... | End Site { OFFSET x y z })* }``: appends
    the joint, then its children, depth first; returns the channel count after them."""
    keyword = syntax.take()
    name = syntax.take("a joint name")
    joint = BvhJoint(name, parent, np.zeros(3), [])
    joints.append(joint)
    index = len(joints) - 1
    syntax.expect("{", f"after {keyword} {name}")
    while (token := syntax.peek()) != "}":
        if token == "OFFSET":
            syntax.take()
            joint.offset = np.array(syntax.numbers(3, f"OFFSET of {name}"))
        elif token == "CHANNELS":
            joint.channels, joint.channel_start = parse_channels(syntax, name), channel_count
            channel_count += len(joint.channels)
        elif token == "JOINT":
            channel_count = parse_joint(syntax, joints, index, channel_count)
        elif token == "End":
            joint.end_site = parse_end_site(syntax, name)
        elif token is None or token == "MOTION":
            syntax.fail(f"unbalanced braces: joint {name} is not closed")
        else:
            syntax.fail(f"unexpected token {token!r} in joint {name}")
    syntax.take()
    return channel_count


def parse_channels(syntax: BvhSyntax, owner: str) -> list[str]:
    """``CHANNELS n name ...`` with known channel names."""
    syntax.take()
    count = syntax.take("a channel count")
    if not count.isdigit():
        syntax.fail(f"CHANNELS of {owner} needs a count, got {count!r}")
    names = [syntax.take("a channel name") for _ in range(int(count))]
    bad = [c for c in names if c not in POSITION_CHANNELS + ROTATION_CHANNELS]
    if bad:
        syntax.fail(f"unknown channels {bad} in joint {owner}")
    return names


def parse_end_site(syntax: BvhSyntax, owner: str) -> np.ndarray:
    """``End Site { OFFSET x y z }`` (an End Site carries no motion: ``CHANNELS 0`` is tolerated, more is not)."""
    syntax.take()
    syntax.expect("Site", "after End")
    syntax.expect("{", f"after End Site of {owner}")
    offset = np.zeros(3)
    while (token := syntax.peek()) != "}":
        if token == "OFFSET":
            syntax.take()
            offset = np.array(syntax.numbers(3, f"OFFSET of the End Site of {owner}"))
        elif token == "CHANNELS":
            if parse_channels(syntax, f"{owner}'s End Site"):
                syntax.fail(f"the End Site of {owner} lists channels; an End Site carries no motion")
        else:
            syntax.fail(f"unexpected token {token!r} in the End Site of {owner}")
    syntax.take()
    return offset


def parse_motion(text: str, channel_count: int, fail) -> tuple[float, np.ndarray]:
    """``Frames: n``, ``Frame Time: dt``, then n rows of ``channel_count`` numbers."""
    frames_match = re.search(r"Frames:\s*(\d+)", text)
    time_match = re.search(r"Frame\s+Time:\s*([0-9.eE+-]+)", text)
    if not frames_match or not time_match:
        fail("MOTION lacks 'Frames:' or 'Frame Time:'")
    n_frames, frame_time = int(frames_match.group(1)), float(time_match.group(1))
    if not frame_time > 0:
        fail(f"Frame Time must be positive, got {frame_time}")
    try:
        values = np.array(text[time_match.end() :].split(), dtype=np.float64)
    except ValueError:
        fail("non-numeric values in MOTION")
    if values.size != n_frames * channel_count:
        fail(f"MOTION holds {values.size} values, expected Frames {n_frames} x {channel_count} channels")
    return frame_time, values.reshape(n_frames, channel_count)


def parse_bvh(text: str, *, source: str | None = None) -> Bvh:
    """Parse BVH text; malformed files raise UserError naming ``source`` (and the line, in the HIERARCHY).

    The MOTION section starts at the first line holding only the word ``MOTION``, so a joint may be named
    anything; joints (several ROOTs allowed) are listed depth first, channels numbered in the same order.
    """

    def fail(message: str):
        raise UserError(f"not a valid BVH file: {message}", file=source)

    split = re.search(r"^[ \t]*MOTION[ \t]*\r?$", text, re.MULTILINE)
    if split is None:
        fail("no MOTION section")
    syntax = BvhSyntax(text[: split.start()], source)
    syntax.expect("HIERARCHY", "at the start")
    joints: list[BvhJoint] = []
    channel_count = 0
    while syntax.peek() is not None:
        if syntax.peek() != "ROOT":
            syntax.fail(f"expected ROOT, found {syntax.peek()!r}" + (" (unbalanced braces)" if joints else ""))
        channel_count = parse_joint(syntax, joints, -1, channel_count)
    if not joints:
        fail("no joints")
    frame_time, motion = parse_motion(text[split.end() :], channel_count, fail)
    return Bvh(joints, frame_time, motion, source)


def read_bvh(path, *, field: str | None = None) -> Bvh:
    try:
        text = open(path, encoding="utf-8", errors="replace").read()
    except OSError as exc:
        raise UserError(f"cannot read BVH file ({exc})", file=str(path), field=field) from None
    return parse_bvh(text, source=str(path))


def joint_rotation(bvh: Bvh, name: str, *, field: str | None = None) -> np.ndarray:
    """The joint's local rotation per frame as unit quaternions (frames, 4); identity without rotation channels."""
    joint = bvh.joint(name, field=field)
    order = joint.rotation_order
    if not order:
        q = np.zeros((bvh.frames, 4))
        q[:, 0] = 1.0
        return q
    if len(order) != 3:
        raise UserError(
            f"joint {name!r} has {len(order)} rotation channels; 3 are needed", file=bvh.source, field=field
        )
    degrees = np.stack([bvh.channel(joint, f"{axis}rotation") for axis in order], axis=-1)
    return euler_order_to_quat(np.radians(degrees), order)


def joint_translation(bvh: Bvh, name: str, *, field: str | None = None) -> np.ndarray:
    """The joint's position channels (frames, 3); its constant OFFSET when it has none."""
    joint = bvh.joint(name, field=field)
    columns = [bvh.channel(joint, c) for c in POSITION_CHANNELS]
    if all(c is None for c in columns):
        return np.repeat(joint.offset[None, :], bvh.frames, axis=0)
    return np.stack(
        [c if c is not None else np.full(bvh.frames, joint.offset[k]) for k, c in enumerate(columns)], axis=-1
    )


def format_bvh(joints: list[BvhJoint], motion: np.ndarray, frame_time: float, *, precision: int = 6) -> str:
    """BVH text of a skeleton (joints in depth-first order, parents before children) and its motion rows."""
    motion = np.asarray(motion, dtype=np.float64)
    n_channels = sum(len(j.channels) for j in joints)
    if motion.ndim != 2 or motion.shape[1] != n_channels:
        raise ValueError(f"motion has shape {motion.shape}, expected (frames, {n_channels})")
    if not np.all(np.isfinite(motion)):
        raise ValueError("motion holds NaN or Inf")
    children: dict[int, list[int]] = {}
    for index, joint in enumerate(joints):
        children.setdefault(joint.parent, []).append(index)
    lines = ["HIERARCHY"]

    def emit(index: int, depth: int):
        joint = joints[index]
        pad = "  " * depth
        keyword = "ROOT" if joint.parent < 0 else "JOINT"
        lines.append(f"{pad}{keyword} {joint.name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {' '.join(f'{v:.{precision}f}' for v in joint.offset)}")
        lines.append(f"{pad}  CHANNELS {len(joint.channels)} {' '.join(joint.channels)}")
        kids = children.get(index, [])
        for child in kids:
            emit(child, depth + 1)
        if not kids:
            end = joint.end_site if joint.end_site is not None else np.array([0.0, 10.0, 0.0])
            lines.append(f"{pad}  End Site")
            lines.append(f"{pad}  {{")
            lines.append(f"{pad}    OFFSET {' '.join(f'{v:.{precision}f}' for v in end)}")
            lines.append(f"{pad}  }}")
        lines.append(f"{pad}}}")

    for root in children.get(-1, []):
        emit(root, 0)
    lines.append("MOTION")
    lines.append(f"Frames: {motion.shape[0]}")
    lines.append(f"Frame Time: {frame_time:.8f}")
    fmt = f"%.{precision}f"
    body = "\n".join(" ".join(fmt % v for v in row) for row in motion)
    return "\n".join(lines) + "\n" + body + ("\n" if body else "")


def head_bvh(
    rotation: np.ndarray,
    translation: np.ndarray | None,
    fps: float,
    *,
    joint: str = "Head",
    order: str = "ZXY",
    end_site: tuple[float, float, float] = (0.0, 10.0, 0.0),
) -> str:
    """BVH text of one root joint carrying the head's rotation (unit quaternions) and translation per frame."""
    rotation = np.asarray(rotation, dtype=np.float64)
    frames = rotation.shape[0]
    translation = np.zeros((frames, 3)) if translation is None else np.asarray(translation, dtype=np.float64)
    degrees = np.degrees(np.unwrap(quat_to_euler_order(rotation, order), axis=0))
    channels = list(POSITION_CHANNELS) + [f"{axis}rotation" for axis in order.upper()]
    root = BvhJoint(joint, -1, np.zeros(3), channels, 0, np.asarray(end_site, dtype=np.float64))
    return format_bvh([root], np.concatenate([translation, degrees], axis=1), 1.0 / fps)
