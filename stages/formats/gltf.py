"""glTF 2.0 reading and writing of a morph-target character (pygltflib), with morph-weight and head animation.

Reading (``read_morph_mesh``) flattens one mesh (all its triangle primitives) into shared vertex arrays, morph
deltas and per-triangle material groups, in the coordinates of the scene (the mesh node's world transform applied).
Writing (``write_morph_glb``) produces a binary GLB the Khronos glTF Validator accepts without errors or
warnings: morph deltas as SPARSE accessors (only the vertices a target moves are stored), min/max on every POSITION
accessor, unit normals and quaternions, strictly increasing key times, plain Python numbers in the JSON (pygltflib
silently writes an empty file when handed numpy scalars).

glTF conventions used: metres, +y up, the character faces +z; quaternions in glTF are (x, y, z, w) while
``stages.geometry.rotations`` uses (w, x, y, z): conversion happens here and nowhere else.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from msflow import UserError

COMPONENT_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
MODE_TRIANGLES, MODE_TRIANGLE_STRIP, MODE_TRIANGLE_FAN = 4, 5, 6
#: required extensions that need nothing beyond this reader (quantized accessors are plain accessors + node scale)
SUPPORTED_REQUIRED_EXTENSIONS = {"KHR_mesh_quantization", "KHR_materials_unlit", "KHR_texture_transform"}
#: morph deltas smaller than this (scene units, metres) are not stored: 10 micrometres is far below visibility
DEFAULT_SPARSE_TOLERANCE = 1e-5


@dataclass
class MaterialGroup:
    """A named material of a set of triangles: base colour RGBA in [0, 1] (linear, as glTF stores it)."""

    name: str
    color: tuple[float, float, float, float] = (0.7, 0.7, 0.7, 1.0)
    double_sided: bool = False


@dataclass
class MorphMesh:
    """A triangle mesh with morph targets, flattened from one glTF mesh (or built from OBJ files)."""

    positions: np.ndarray  # (V, 3) float32
    triangles: np.ndarray  # (T, 3) int32
    target_names: list[str]
    deltas: np.ndarray  # (M, V, 3) float32
    triangle_groups: np.ndarray | None = None  # (T,) int32 index into groups
    groups: list[MaterialGroup] = field(default_factory=list)
    extras: dict[str, Any] = field(default_factory=dict)  # mesh.extras (targetNames, landmark ids, ...)
    name: str = "Character"

    def __post_init__(self):
        if self.triangle_groups is None:
            self.triangle_groups = np.zeros(len(self.triangles), dtype=np.int32)
        if not self.groups:
            self.groups = [MaterialGroup("default")]


@dataclass
class Animation:
    """Keyframes sampled at ``times`` (seconds, strictly increasing), played with LINEAR interpolation.

    ``weights`` (frames, M) drive the morph targets in the mesh's target order; ``rotation`` (frames, 4) is in the
    stages.geometry.rotations (w, x, y, z) convention and ``translation`` (frames, 3) in metres: both animate the
    head (the ``Head`` joint of a Skeleton, else a ``Head`` node), which turns about ``pivot`` (a point in mesh
    coordinates, e.g. the top of the neck; a Skeleton's Head joint position replaces it).
    ``joint_rotations`` {joint name: (frames, 4)} turn other joints of a Skeleton relative to their parent (eyes).
    """

    times: np.ndarray
    weights: np.ndarray | None = None
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    joint_rotations: dict[str, np.ndarray] = field(default_factory=dict)
    name: str = "performance"


@dataclass
class Skeleton:
    """Joints of a rigidly skinned mesh: every vertex follows exactly one joint (weight 1).

    ``positions`` (J, 3) are the joints' bind positions in mesh coordinates (their rest orientation is the
    identity); ``parents[j]`` < j, -1 for the root; ``vertex_joint`` (V,) the joint each vertex follows. The
    joint named ``HEAD_JOINT`` carries the head motion of an Animation.
    """

    names: list[str]
    parents: list[int]
    positions: np.ndarray
    vertex_joint: np.ndarray

    def __post_init__(self):
        self.positions = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        self.vertex_joint = np.asarray(self.vertex_joint, dtype=np.int64)
        if not (len(self.names) == len(self.parents) == len(self.positions)):
            raise ValueError("a skeleton needs one name, parent and position per joint")
        if any(not (-1 <= p < j) for j, p in enumerate(self.parents)) or self.parents[0] != -1:
            raise ValueError(f"joint parents must come first and the first joint be the root: {self.parents}")
        if len(self.vertex_joint) and not (0 <= self.vertex_joint.min() and self.vertex_joint.max() < len(self.names)):
            raise ValueError("vertex_joint holds an index outside the joints")

    def local_translation(self, j: int) -> np.ndarray:
        """Bind translation of joint ``j`` relative to its parent."""
        parent = self.parents[j]
        return self.positions[j] - (self.positions[parent] if parent >= 0 else 0.0)


HEAD_JOINT = "Head"


# ----------------------------------------------------------------------------------------------------- reading


def _load_gltf(path: Path):
    import pygltflib

    try:
        gltf = pygltflib.GLTF2().load(str(path))
    except Exception as exc:  # pygltflib raises assorted errors (json, struct, KeyError) on broken files
        raise UserError(f"cannot read as glTF 2.0 ({type(exc).__name__}: {exc})", file=str(path)) from None
    if gltf is None:
        raise UserError("cannot read as glTF 2.0 (unknown file type; expected .glb or .gltf)", file=str(path))
    return gltf


def _buffer_bytes(gltf, path: Path) -> list[bytes]:
    """The bytes of every buffer: the GLB binary chunk, a data: URI, or a file next to the .gltf."""
    blobs = []
    for i, buffer in enumerate(gltf.buffers):
        uri = buffer.uri
        if uri is None:
            data = gltf.binary_blob()
        elif uri.startswith("data:"):
            data = base64.b64decode(uri.split(",", 1)[1])
        else:
            target = path.parent / uri
            if not target.is_file():
                raise UserError(f"buffer {i} refers to '{uri}', which does not exist next to the file", file=str(path))
            data = target.read_bytes()
        if data is None or len(data) < (buffer.byteLength or 0):
            raise UserError(f"buffer {i} is shorter than its declared byteLength", file=str(path))
        blobs.append(bytes(data))
    return blobs


def _read_view(
    gltf, blobs: list[bytes], view_index: int, byte_offset: int, dtype, count: int, ncomp: int, path: Path
) -> np.ndarray:
    view = gltf.bufferViews[view_index]
    blob = blobs[view.buffer]
    itemsize = np.dtype(dtype).itemsize
    stride = view.byteStride or itemsize * ncomp
    start = (view.byteOffset or 0) + (byte_offset or 0)
    if count == 0:
        return np.zeros((0, ncomp), dtype=dtype)
    need = stride * (count - 1) + itemsize * ncomp
    if start + need > len(blob):
        raise UserError(f"bufferView {view_index} reads past the end of its buffer", file=str(path))
    if stride == itemsize * ncomp:
        return np.frombuffer(blob, dtype=dtype, count=count * ncomp, offset=start).reshape(count, ncomp)
    return _strided(blob, start, stride, dtype, count, ncomp)


def _strided(blob: bytes, start: int, stride: int, dtype, count: int, ncomp: int) -> np.ndarray:
    """Interleaved vertex data: gather ``count`` records of ``ncomp`` values ``stride`` bytes apart."""
    itemsize = np.dtype(dtype).itemsize
    rows = np.frombuffer(blob, dtype=np.uint8, count=stride * (count - 1) + itemsize * ncomp, offset=start)
    index = np.arange(count)[:, None] * stride + np.arange(itemsize * ncomp)[None, :]
    return rows[index].copy().view(dtype).reshape(count, ncomp)


def read_accessor(gltf, blobs: list[bytes], index: int, path: Path) -> np.ndarray:
    """Accessor ``index`` as a (count, components) array: strides, normalisation and sparse substitution applied.

    Integer accessors stay integer unless ``normalized`` (then float32 in [0, 1] or [-1, 1] per the spec).
    """
    acc = gltf.accessors[index]
    dtype = COMPONENT_DTYPES.get(acc.componentType)
    if dtype is None or acc.type not in TYPE_SIZES:
        raise UserError(
            f"accessor {index} has unsupported componentType {acc.componentType} / type {acc.type}", file=str(path)
        )
    ncomp = TYPE_SIZES[acc.type]
    if acc.bufferView is None:
        data = np.zeros((acc.count, ncomp), dtype=dtype)
    else:
        data = _read_view(gltf, blobs, acc.bufferView, acc.byteOffset, dtype, acc.count, ncomp, path).copy()
    if acc.sparse is not None and acc.sparse.count:
        sparse = acc.sparse
        idx_dtype = COMPONENT_DTYPES[sparse.indices.componentType]
        ids = _read_view(
            gltf, blobs, sparse.indices.bufferView, sparse.indices.byteOffset, idx_dtype, sparse.count, 1, path
        )[:, 0].astype(np.int64)
        values = _read_view(
            gltf, blobs, sparse.values.bufferView, sparse.values.byteOffset, dtype, sparse.count, ncomp, path
        )
        if ids.size and (ids.min() < 0 or ids.max() >= acc.count):
            raise UserError(f"accessor {index}: sparse indices out of range", file=str(path))
        data[ids] = values
    if acc.normalized and dtype is not np.float32:
        info = np.iinfo(dtype)
        data = data.astype(np.float32) / float(info.max)
        if info.min < 0:
            data = np.maximum(data, -1.0)
    return data


def _node_world_matrices(gltf) -> dict[int, np.ndarray]:
    """World matrix of every node reachable from the scenes (or every root node when there is no scene)."""

    def local(node) -> np.ndarray:
        if node.matrix:
            return np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF stores column-major
        from stages.geometry.rotations import quat_to_matrix

        m = np.eye(4)
        scale = np.asarray(node.scale if node.scale else [1, 1, 1], dtype=np.float64)
        if node.rotation:
            x, y, z, w = node.rotation
            m[:3, :3] = quat_to_matrix(np.array([w, x, y, z]))
        m[:3, :3] = m[:3, :3] * scale[None, :]
        if node.translation:
            m[:3, 3] = node.translation
        return m

    worlds: dict[int, np.ndarray] = {}
    children = {c for node in gltf.nodes for c in (node.children or [])}
    roots = [i for i in range(len(gltf.nodes)) if i not in children]
    stack = [(r, np.eye(4)) for r in roots]
    while stack:
        i, parent = stack.pop()
        if i in worlds:
            continue
        worlds[i] = parent @ local(gltf.nodes[i])
        stack.extend((c, worlds[i]) for c in (gltf.nodes[i].children or []))
    return worlds


def _triangulate(indices: np.ndarray, mode: int) -> np.ndarray:
    if mode == MODE_TRIANGLES:
        return indices[: len(indices) // 3 * 3].reshape(-1, 3)
    n = len(indices)
    if n < 3:
        return np.zeros((0, 3), dtype=indices.dtype)
    k = np.arange(n - 2)
    if mode == MODE_TRIANGLE_FAN:
        return np.stack([np.full(n - 2, indices[0]), indices[k + 1], indices[k + 2]], axis=1)
    # strip: every other triangle flips its winding to keep a consistent orientation
    even = k % 2 == 0
    a = np.where(even, indices[k], indices[k + 1])
    b = np.where(even, indices[k + 1], indices[k])
    return np.stack([a, b, indices[k + 2]], axis=1)


def _target_names(mesh, count: int) -> tuple[list[str], str]:
    for where, extras in (("mesh.extras", mesh.extras), ("primitive.extras", mesh.primitives[0].extras)):
        names = (extras or {}).get("targetNames")
        if names is not None:
            if len(names) != count or not all(isinstance(n, str) for n in names):
                raise UserError(f"{where}.targetNames lists {len(names)} names but the mesh has {count} morph targets")
            return list(names), where
    return [f"target_{i:03d}" for i in range(count)], "generated"


def read_morph_mesh(path: str | Path, mesh_name: str | None = None) -> MorphMesh:
    """Read one mesh with morph targets from a .glb/.gltf file, in scene coordinates.

    ``mesh_name`` picks a mesh by name; by default the first mesh that has morph targets. Target names come from
    ``mesh.extras.targetNames`` (the de-facto convention of Blender, three.js and others). Triangle primitives
    that share a POSITION accessor share vertices; other primitives are appended.
    """
    path = Path(path)
    gltf = _load_gltf(path)
    unsupported = sorted(set(gltf.extensionsRequired or []) - SUPPORTED_REQUIRED_EXTENSIONS)
    if unsupported:
        raise UserError(
            f"the file requires glTF extensions this reader does not decode: {unsupported} (e.g. "
            f"Draco or meshopt compression); export it again without them",
            file=str(path),
        )
    mesh_index = _choose_mesh(gltf.meshes or [], mesh_name, path)
    mesh = gltf.meshes[mesh_index]
    counts = {len(p.targets or []) for p in mesh.primitives if p.targets}
    if len(counts) != 1:
        raise UserError(
            f"mesh '{mesh.name}': primitives disagree on the number of morph targets {sorted(counts)}", file=str(path)
        )
    n_targets = counts.pop()
    names, names_from = _target_names(mesh, n_targets)
    out = _read_primitives(gltf, _buffer_bytes(gltf, path), mesh, n_targets, path)
    out.target_names, out.name = names, mesh.name or f"mesh{mesh_index}"
    out.extras = dict(mesh.extras or {}, _target_names_from=names_from)
    _apply_world_transform(out, gltf, mesh_index)
    return out


def _choose_mesh(meshes: list, mesh_name: str | None, path: Path) -> int:
    """The mesh named ``mesh_name`` (it must have morph targets), else the first mesh with morph targets."""
    with_targets = [i for i, m in enumerate(meshes) if any(p.targets for p in m.primitives)]
    if mesh_name is None:
        if not with_targets:
            raise UserError(
                "the character has no morph targets (no mesh primitive lists 'targets'); export the "
                "blendshapes/shape keys with the mesh",
                file=str(path),
            )
        return with_targets[0]
    matches = [i for i, m in enumerate(meshes) if m.name == mesh_name]
    if not matches:
        raise UserError(
            f"no mesh named '{mesh_name}'; meshes: {[m.name for m in meshes]}",
            file=str(path),
            field="params.mesh_name",
        )
    if matches[0] not in with_targets:
        raise UserError(f"mesh '{mesh_name}' has no morph targets", file=str(path), field="params.mesh_name")
    return matches[0]


def _read_primitives(gltf, blobs: list[bytes], mesh, n_targets: int, path: Path) -> MorphMesh:
    """The mesh's triangle primitives flattened: shared vertex arrays (one block per POSITION accessor), morph
    deltas, triangles and a material group per triangle (names filled in by the caller)."""
    positions, deltas, triangles, tri_groups = [], [], [], []
    groups: list[MaterialGroup] = []
    group_of_material: dict[Any, int] = {}
    offset_of_position: dict[int, int] = {}
    for p_index, prim in enumerate(mesh.primitives):
        mode = MODE_TRIANGLES if prim.mode is None else prim.mode
        if mode not in (MODE_TRIANGLES, MODE_TRIANGLE_STRIP, MODE_TRIANGLE_FAN) or prim.attributes.POSITION is None:
            continue  # points and lines carry no surface
        pos_acc = prim.attributes.POSITION
        if pos_acc not in offset_of_position:
            offset_of_position[pos_acc] = sum(len(p) for p in positions)
            pos, d = _vertices_and_deltas(gltf, blobs, prim, n_targets, path)
            positions.append(pos)
            deltas.append(d)
        idx = _primitive_indices(gltf, blobs, prim, mesh.name, p_index, path)
        tris = _triangulate(idx, mode) + offset_of_position[pos_acc]
        if prim.material not in group_of_material:
            group_of_material[prim.material] = len(groups)
            groups.append(_material_group(gltf, prim.material, p_index))
        triangles.append(tris)
        tri_groups.append(np.full(len(tris), group_of_material[prim.material], dtype=np.int32))
    if not positions:
        raise UserError(f"mesh '{mesh.name}' has no triangle primitives", file=str(path))
    return MorphMesh(
        positions=np.concatenate(positions),
        triangles=np.concatenate(triangles).astype(np.int32),
        target_names=[],
        deltas=np.concatenate(deltas, axis=1),
        triangle_groups=np.concatenate(tri_groups),
        groups=groups,
    )


def _vertices_and_deltas(gltf, blobs: list[bytes], prim, n_targets: int, path: Path):
    """A primitive's POSITION (V, 3) and its morph targets' POSITION deltas (n_targets, V, 3), float32."""
    pos = read_accessor(gltf, blobs, prim.attributes.POSITION, path).astype(np.float32)
    d = np.zeros((n_targets, len(pos), 3), dtype=np.float32)
    for t, target in enumerate(prim.targets or []):
        t_pos = target.get("POSITION") if isinstance(target, dict) else getattr(target, "POSITION", None)
        if t_pos is not None:
            d[t] = read_accessor(gltf, blobs, t_pos, path)
    return pos, d


def _primitive_indices(gltf, blobs: list[bytes], prim, mesh_name: str, p_index: int, path: Path) -> np.ndarray:
    """A primitive's vertex indices (all its vertices in order when it has none), checked against its vertices."""
    count = gltf.accessors[prim.attributes.POSITION].count
    if prim.indices is None:
        return np.arange(count, dtype=np.int64)
    idx = read_accessor(gltf, blobs, prim.indices, path)[:, 0].astype(np.int64)
    if idx.size and idx.max() >= count:
        raise UserError(
            f"mesh '{mesh_name}' primitive {p_index}: vertex index {int(idx.max())} out of range ({count} vertices)",
            file=str(path),
        )
    return idx


def _material_group(gltf, material_index, primitive_index: int) -> MaterialGroup:
    if material_index is None:
        return MaterialGroup(f"primitive{primitive_index}")
    mat = gltf.materials[material_index]
    color = (0.8, 0.8, 0.8, 1.0)
    if mat.pbrMetallicRoughness is not None and mat.pbrMetallicRoughness.baseColorFactor:
        color = tuple(float(c) for c in mat.pbrMetallicRoughness.baseColorFactor)
    return MaterialGroup(mat.name or f"material{material_index}", color, bool(mat.doubleSided))


def _apply_world_transform(mesh: MorphMesh, gltf, mesh_index: int) -> None:
    users = [i for i, n in enumerate(gltf.nodes or []) if n.mesh == mesh_index]
    if not users:
        return
    world = _node_world_matrices(gltf).get(users[0])
    if world is None or np.allclose(world, np.eye(4)):
        return
    linear = world[:3, :3]
    mesh.positions = (mesh.positions @ linear.T + world[:3, 3]).astype(np.float32)
    mesh.deltas = (mesh.deltas @ linear.T).astype(np.float32)
    if np.linalg.det(linear) < 0:  # a mirroring transform turns the winding inside out
        mesh.triangles = mesh.triangles[:, ::-1].copy()


# ----------------------------------------------------------------------------------------------------- writing


class _BinaryBuilder:
    """Accumulates the GLB binary chunk and the bufferViews/accessors pointing into it."""

    def __init__(self, gltf):
        self.gltf = gltf
        self.chunks: list[bytes] = []
        self.length = 0

    def view(self, data: np.ndarray, target: int | None = None) -> int:
        import pygltflib

        raw = np.ascontiguousarray(data).tobytes()
        pad = (-self.length) % 4
        if pad:
            self.chunks.append(b"\0" * pad)
            self.length += pad
        self.gltf.bufferViews.append(
            pygltflib.BufferView(buffer=0, byteOffset=int(self.length), byteLength=len(raw), target=target)
        )
        self.chunks.append(raw)
        self.length += len(raw)
        return len(self.gltf.bufferViews) - 1

    def accessor(
        self, data: np.ndarray, kind: str, *, target: int | None = None, min_max: bool = False, name: str | None = None
    ) -> int:
        import pygltflib

        data = np.asarray(data)
        ncomp = TYPE_SIZES[kind]
        flat = data.reshape(-1, ncomp) if ncomp > 1 else data.reshape(-1)
        component = {
            np.dtype(np.float32): 5126,
            np.dtype(np.uint16): 5123,
            np.dtype(np.uint32): 5125,
            np.dtype(np.uint8): 5121,
        }[flat.dtype]
        acc = pygltflib.Accessor(
            bufferView=self.view(flat, target),
            byteOffset=0,
            componentType=component,
            count=int(len(flat)),
            type=kind,
            name=name,
        )
        if min_max:
            acc.min, acc.max = _min_max(flat.reshape(len(flat), -1))
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    def sparse_accessor(
        self, values: np.ndarray, tolerance: float, name: str | None = None, moving: np.ndarray | None = None
    ) -> int:
        """A VEC3 float accessor of len(values) elements storing only rows with a component above ``tolerance``
        (``moving``: those rows' mask, when already known)."""
        import pygltflib

        values = np.asarray(values, dtype=np.float32)
        keep = np.flatnonzero(moving_rows(values, tolerance) if moving is None else moving)
        index_size = 2 if len(values) <= 65535 else 4
        if len(keep) * (12 + index_size) >= 12 * len(values):  # a dense target (identity shape) is smaller as is
            return self.accessor(values, "VEC3", target=ARRAY_BUFFER, min_max=True, name=name)
        acc = pygltflib.Accessor(
            bufferView=None, byteOffset=None, componentType=5126, count=int(len(values)), type="VEC3", name=name
        )
        stored = np.zeros_like(values)
        stored[keep] = values[keep]
        acc.min, acc.max = _min_max(stored)
        if len(keep):
            index_dtype = np.uint16 if index_size == 2 else np.uint32
            acc.sparse = pygltflib.Sparse(
                count=int(len(keep)),
                indices=pygltflib.AccessorSparseIndices(
                    bufferView=self.view(keep.astype(index_dtype)),
                    byteOffset=0,
                    componentType=5123 if index_dtype is np.uint16 else 5125,
                ),
                values=pygltflib.AccessorSparseValues(bufferView=self.view(values[keep]), byteOffset=0),
            )
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    def blob(self) -> bytes:
        data = b"".join(self.chunks)
        return data + b"\0" * ((-len(data)) % 4)


def moving_rows(values: np.ndarray, tolerance: float) -> np.ndarray:
    """Mask of the (..., 3) rows with a component above ``tolerance`` in absolute value."""
    a = np.abs(values)
    return np.maximum(np.maximum(a[..., 0], a[..., 1]), a[..., 2]) > tolerance


def _min_max(flat: np.ndarray) -> tuple[list[float], list[float]]:
    if len(flat) == 0:
        return [0.0] * flat.shape[1], [0.0] * flat.shape[1]
    return [float(v) for v in flat.min(axis=0)], [float(v) for v in flat.max(axis=0)]


def _plain(value: Any) -> Any:
    """numpy scalars and arrays to plain Python (pygltflib's JSON encoder writes nothing for numpy types)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value


def write_morph_glb(
    mesh: MorphMesh,
    *,
    animation: Animation | None = None,
    skeleton: Skeleton | None = None,
    sparse_tolerance: float = DEFAULT_SPARSE_TOLERANCE,
    generator: str = "msflow",
    copyright: str | None = None,
    normals: bool = True,
    scene_extras: dict | None = None,
) -> bytes:
    """The character as a GLB: one mesh (a primitive per material group, all sharing the vertex and morph
    accessors), morph targets as sparse accessors, names in ``mesh.extras.targetNames``.

    Node layout without a skeleton: ``Head`` (turns about ``animation.pivot``; carries the head rotation and
    translation) with child ``<mesh.name>`` (offset by -pivot; carries the mesh and its morph-weight animation),
    so an animator can re-pose the head without touching the face animation.
    With a ``skeleton``: its joints as a node tree (the first joint the root), and a root node ``<mesh.name>``
    holding the mesh skinned to them (JOINTS_0/WEIGHTS_0, inverse bind matrices) and the morph-weight
    animation; head motion goes to the ``Head`` joint, ``animation.joint_rotations`` to the joints they name.
    Engines that keep morph targets on skinned meshes only (Unreal) need this layout.
    """
    import pygltflib

    positions = np.ascontiguousarray(mesh.positions, dtype=np.float32)
    n_vertices, n_targets = len(positions), len(mesh.target_names)
    if np.asarray(mesh.deltas).shape != (n_targets, n_vertices, 3):
        raise ValueError(f"deltas {np.shape(mesh.deltas)} do not match {n_targets} targets x {n_vertices} vertices")
    if n_targets == 0:
        raise ValueError("a morph-target character needs at least one target")
    if skeleton is not None and len(skeleton.vertex_joint) != n_vertices:
        raise ValueError(f"the skeleton binds {len(skeleton.vertex_joint)} vertices, the mesh has {n_vertices}")

    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(generator=generator, copyright=copyright))
    gltf.bufferViews, gltf.accessors = [], []
    bin_ = _BinaryBuilder(gltf)
    attributes = _vertex_attributes(bin_, mesh, normals, skeleton)
    _add_mesh(gltf, bin_, mesh, attributes, sparse_tolerance)
    pivot = [float(v) for v in (animation.pivot if animation is not None else (0.0, 0.0, 0.0))]
    if skeleton is None:
        nodes = _plain_nodes(gltf, mesh.name, pivot)
    else:
        nodes = _skinned_nodes(gltf, bin_, mesh.name, skeleton)
        pivot = (
            [float(v) for v in skeleton.positions[nodes["joints"][HEAD_JOINT]]]
            if HEAD_JOINT in nodes["joints"]
            else pivot
        )
    gltf.scene = 0
    gltf.scenes = [pygltflib.Scene(name="Scene", nodes=nodes["roots"], extras=_plain(scene_extras or {}))]
    if animation is not None:
        gltf.animations = [_animation(bin_, animation, n_targets, nodes, skeleton, pivot)]
    gltf.buffers = [pygltflib.Buffer(byteLength=0)]
    blob = bin_.blob()
    gltf.buffers[0].byteLength = len(blob)
    gltf.set_binary_blob(blob)
    return b"".join(gltf.save_to_bytes())


def _vertex_attributes(bin_: _BinaryBuilder, mesh: MorphMesh, normals: bool, skeleton: Skeleton | None) -> dict:
    positions = np.ascontiguousarray(mesh.positions, dtype=np.float32)
    attributes = {"POSITION": bin_.accessor(positions, "VEC3", target=ARRAY_BUFFER, min_max=True, name="positions")}
    if normals:
        from stages.geometry.render import vertex_normals

        attributes["NORMAL"] = bin_.accessor(
            vertex_normals(positions, np.asarray(mesh.triangles)), "VEC3", target=ARRAY_BUFFER, name="normals"
        )
    if skeleton is not None:
        # rigid skinning: one influence of weight 1; the unused three point at joint 0 with weight 0
        joints = np.zeros((len(positions), 4), dtype=np.uint8 if len(skeleton.names) <= 256 else np.uint16)
        joints[:, 0] = skeleton.vertex_joint
        weights = np.zeros((len(positions), 4), dtype=np.float32)
        weights[:, 0] = 1.0
        attributes["JOINTS_0"] = bin_.accessor(joints, "VEC4", target=ARRAY_BUFFER, name="joints")
        attributes["WEIGHTS_0"] = bin_.accessor(weights, "VEC4", target=ARRAY_BUFFER, name="skin weights")
    return attributes


def _add_mesh(gltf, bin_: _BinaryBuilder, mesh: MorphMesh, attributes: dict, sparse_tolerance: float) -> None:
    """The mesh: morph targets as sparse accessors, one primitive and material per non-empty material group."""
    import pygltflib

    deltas = np.asarray(mesh.deltas, dtype=np.float32)
    moving = moving_rows(deltas, sparse_tolerance)  # (targets, vertices), all targets at once
    targets = [
        pygltflib.Attributes(POSITION=bin_.sparse_accessor(deltas[i], sparse_tolerance, name=name, moving=moving[i]))
        for i, name in enumerate(mesh.target_names)
    ]
    triangles = np.asarray(mesh.triangles)
    index_dtype = np.uint16 if len(mesh.positions) < 65535 else np.uint32  # 65535 is the primitive-restart value
    groups = np.asarray(mesh.triangle_groups)
    primitives = []
    gltf.materials = []
    for g, group in enumerate(mesh.groups):
        tris = triangles[groups == g]
        if len(tris) == 0:
            continue
        gltf.materials.append(_material(group))
        indices = bin_.accessor(
            tris.reshape(-1).astype(index_dtype), "SCALAR", target=ELEMENT_ARRAY_BUFFER, name=f"{group.name} triangles"
        )
        primitives.append(
            pygltflib.Primitive(
                attributes=pygltflib.Attributes(**attributes),
                mode=MODE_TRIANGLES,
                indices=indices,
                material=len(gltf.materials) - 1,
                targets=targets,
            )
        )
    extras = {k: v for k, v in mesh.extras.items() if not k.startswith("_")}
    extras["targetNames"] = list(mesh.target_names)
    weights = [0.0] * len(mesh.target_names)
    gltf.meshes = [pygltflib.Mesh(name=mesh.name, primitives=primitives, weights=weights, extras=_plain(extras))]


def _material(group: MaterialGroup):
    import pygltflib

    return pygltflib.Material(
        name=group.name,
        doubleSided=bool(group.double_sided),
        alphaMode="BLEND" if group.color[3] < 1.0 else "OPAQUE",
        pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
            baseColorFactor=[float(c) for c in group.color], metallicFactor=0.0, roughnessFactor=0.6
        ),
    )


def _plain_nodes(gltf, name: str, pivot: list[float]) -> dict:
    """Head node at the pivot with the mesh node as its child, offset back by -pivot."""
    import pygltflib

    head = pygltflib.Node(name=HEAD_JOINT, children=[1], translation=pivot if any(pivot) else None)
    body = pygltflib.Node(name=name, mesh=0, translation=[-v for v in pivot] if any(pivot) else None)
    gltf.nodes = [head, body]
    return {"roots": [0], "mesh": 1, "joints": {HEAD_JOINT: 0}}


def _skinned_nodes(gltf, bin_: _BinaryBuilder, name: str, skeleton: Skeleton) -> dict:
    """Joint nodes 0..J-1 (identity rest rotations, bind translations), then the skinned mesh node J."""
    import pygltflib

    count = len(skeleton.names)
    gltf.nodes = [
        pygltflib.Node(
            name=joint,
            translation=[float(v) for v in skeleton.local_translation(j)] or None,
            children=[c for c in range(count) if skeleton.parents[c] == j] or None,
        )
        for j, joint in enumerate(skeleton.names)
    ]
    # inverse bind matrix of a joint at p with identity rotation: translate by -p (column-major storage)
    inverse_bind = np.tile(np.eye(4, dtype=np.float32), (count, 1, 1))
    inverse_bind[:, :3, 3] = -skeleton.positions
    ibm = bin_.accessor(np.ascontiguousarray(inverse_bind.transpose(0, 2, 1)), "MAT4", name="inverse bind matrices")
    gltf.skins = [pygltflib.Skin(name="Skeleton", joints=list(range(count)), skeleton=0, inverseBindMatrices=ibm)]
    gltf.nodes.append(pygltflib.Node(name=name, mesh=0, skin=0))
    return {"roots": [0, count], "mesh": count, "joints": {joint: j for j, joint in enumerate(skeleton.names)}}


def _animation(bin_: _BinaryBuilder, anim: Animation, n_targets: int, nodes: dict, skeleton, pivot: list[float]):
    """Samplers and channels: morph weights on the mesh node, head motion on the head, joint rotations."""
    import pygltflib

    times = np.asarray(anim.times, dtype=np.float32)
    if times.ndim != 1 or len(times) == 0:
        raise ValueError("animation times must be a non-empty 1-D array")
    if len(times) > 1 and not np.all(np.diff(times) > 0):
        raise ValueError("animation times must increase strictly (after float32 rounding)")
    out = pygltflib.Animation(name=anim.name, channels=[], samplers=[])
    time_acc = bin_.accessor(times, "SCALAR", min_max=True, name="time")

    def channel(values: np.ndarray, kind: str, node: int, path: str, name: str) -> None:
        sampler = pygltflib.AnimationSampler(
            input=time_acc, output=bin_.accessor(values, kind, name=name), interpolation="LINEAR"
        )
        out.samplers.append(sampler)
        target = pygltflib.AnimationChannelTarget(node=node, path=path)
        out.channels.append(pygltflib.AnimationChannel(sampler=len(out.samplers) - 1, target=target))

    for values, kind, node, path, name in _channels(anim, len(times), n_targets, nodes, skeleton, pivot):
        channel(values, kind, node, path, name)
    return out


def _channels(anim: Animation, frames: int, n_targets: int, nodes: dict, skeleton, pivot: list[float]):
    """(values, accessor type, node, path, name) of every animated property, checked against ``frames``."""
    if anim.weights is not None:
        w = np.asarray(anim.weights, dtype=np.float32)
        if w.shape != (frames, n_targets):
            raise ValueError(f"animation weights {w.shape}, expected {(frames, n_targets)}")
        yield w.reshape(-1), "SCALAR", nodes["mesh"], "weights", "morph weights"
    rotations = dict(anim.joint_rotations)
    if anim.rotation is not None:
        rotations[HEAD_JOINT] = anim.rotation
    for joint, rotation in rotations.items():
        if joint not in nodes["joints"]:
            raise ValueError(f"animation turns joint {joint!r}, which the file does not have")
        yield _gltf_quaternions(rotation, frames), "VEC4", nodes["joints"][joint], "rotation", f"{joint} rotation"
    if anim.translation is not None:
        t = np.asarray(anim.translation, dtype=np.float64)
        if t.shape != (frames, 3):
            raise ValueError(f"animation translation {t.shape}, expected {(frames, 3)}")
        head = nodes["joints"][HEAD_JOINT]
        rest = skeleton.local_translation(head) if skeleton is not None else np.asarray(pivot)
        yield (t + rest).astype(np.float32), "VEC3", head, "translation", "head translation"


def _gltf_quaternions(rotation: np.ndarray, frames: int) -> np.ndarray:
    """(w, x, y, z) rotations as glTF's unit (x, y, z, w) float32, signs made continuous for interpolation."""
    from stages.geometry.rotations import quat_continuous, quat_normalize

    q = quat_continuous(quat_normalize(np.asarray(rotation, dtype=np.float64)))
    if q.shape != (frames, 4):
        raise ValueError(f"animation rotation {q.shape}, expected {(frames, 4)}")
    xyzw = q[:, [1, 2, 3, 0]].astype(np.float32)
    return xyzw / np.linalg.norm(xyzw, axis=1, keepdims=True)


# ----------------------------------------------------------------------------------------------------- validation

VALIDATOR_INSTALL = "npm install --no-save --no-package-lock gltf-validator@2.0.0-dev.3.10"
_VALIDATOR_JS = r"""
const fs = require('fs');
const validator = require('gltf-validator');
const data = fs.readFileSync(0);
validator.validateBytes(new Uint8Array(data), {maxIssues: 100}).then((r) => {
  process.stdout.write(JSON.stringify({numErrors: r.issues.numErrors, numWarnings: r.issues.numWarnings,
    numInfos: r.issues.numInfos, numHints: r.issues.numHints, messages: r.issues.messages,
    validatorVersion: r.validatorVersion}));
}, (e) => { process.stderr.write(String(e)); process.exit(3); });
"""


def node_modules_folder(node_modules: str | Path | None = None, package: str = "gltf-validator") -> Path:
    """The node_modules folder holding ``package``: the one given, else $MSFLOW_NODE_MODULES, else the project
    root's. Raises RuntimeError with the install command when the package is in none of them."""
    import os

    from stages.data import PROJECT_ROOT

    candidates = [Path(p) for p in (node_modules, os.environ.get("MSFLOW_NODE_MODULES")) if p]
    candidates.append(PROJECT_ROOT / "node_modules")
    for folder in candidates:
        if (folder / package).is_dir():
            return folder
    raise RuntimeError(
        f"{package} is not installed in {[str(c) for c in candidates]}; install it in a folder and point "
        f"MSFLOW_NODE_MODULES at its node_modules, e.g. in the project root: {VALIDATOR_INSTALL}"
    )


def validate_glb(data: bytes, *, node_modules: str | Path | None = None, timeout: float = 120.0) -> dict:
    """Run the Khronos glTF Validator (npm ``gltf-validator``, via node) on GLB bytes; returns its issue summary
    (numErrors, numWarnings, numInfos, numHints, messages, validatorVersion). The package is looked up by
    ``node_modules_folder`` (install it with VALIDATOR_INSTALL)."""
    import json
    import os
    import shutil
    import subprocess

    node = shutil.which("node")
    if node is None:
        raise RuntimeError("node (Node.js) is not installed; the glTF validator needs it")
    modules = node_modules_folder(node_modules)
    env = dict(os.environ, NODE_PATH=str(modules))
    proc = subprocess.run(
        [node, "-e", _VALIDATOR_JS],
        input=bytes(data),
        capture_output=True,
        cwd=modules.parent,
        env=env,
        timeout=timeout,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"glTF validator failed: {proc.stderr.decode(errors='replace')[:2000]}")
    return json.loads(proc.stdout)
