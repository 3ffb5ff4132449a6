"""Progress display: per-stage state (cached / running / done / failed / skipped) and time.

On a terminal a live rich table; otherwise one line per state change (logs, CI). Both write to stderr.
"""

from __future__ import annotations

import sys
import time

STYLE = {
    "pending": ("·", "dim"),
    "cached": ("=", "cyan"),
    "running": ("…", "yellow"),
    "ran": ("✓", "green"),
    "failed": ("✗", "bold red"),
    "skipped": ("-", "dim"),
    "waiting": ("⏳", "magenta"),
}
LABEL = {"ran": "done"}


class PlainReporter:
    def __init__(self, names: list[str], stream=None):
        self.stream = stream or sys.stderr
        self.width = max((len(n) for n in names), default=8)

    def start(self) -> None:
        pass

    def update(self, state) -> None:
        if state.state == "pending":
            return
        mark, _ = STYLE.get(state.state, ("?", ""))
        timing = f"{state.seconds:7.2f}s" if state.state in ("ran", "failed") and state.seconds else ""
        detail = f"  ({state.detail})" if state.detail else ""
        print(
            f"{mark} {state.name:<{self.width}}  {LABEL.get(state.state, state.state):<8}{timing}{detail}",
            file=self.stream,
            flush=True,
        )

    def stop(self) -> None:
        pass


class RichReporter:
    """A live table; its rows are rebuilt from the latest state of each stage at every refresh."""

    def __init__(self, names: list[str]):
        from rich.console import Console
        from rich.live import Live

        self.rows = {n: ["pending", 0.0, "", None] for n in names}
        self.console = Console(stderr=True)
        self.live = Live(self, console=self.console, refresh_per_second=8, transient=False)

    def __rich__(self):
        from rich.table import Table

        table = Table.grid(padding=(0, 2))
        for name, (state, seconds, detail, since) in self.rows.items():
            mark, style = STYLE.get(state, ("?", ""))
            if state == "running" and since is not None:
                seconds = time.perf_counter() - since
            timing = f"{seconds:.2f}s" if state in ("running", "ran", "failed") else ""
            table.add_row(
                f"[{style}]{mark}[/]", name, f"[{style}]{LABEL.get(state, state)}[/]", timing, f"[dim]{detail}[/]"
            )
        return table

    def start(self) -> None:
        self.live.start()

    def update(self, state) -> None:
        row = self.rows.setdefault(state.name, ["pending", 0.0, "", None])
        row[0], row[1], row[2] = state.state, state.seconds, state.detail
        if state.state == "running":
            row[3] = time.perf_counter()

    def stop(self) -> None:
        self.live.stop()


def make_reporter(names: list[str], quiet: bool = False):
    if quiet:
        return None
    if sys.stderr.isatty():
        return RichReporter(names)
    return PlainReporter(names)


class SweepReporter:
    """One line per variant: how many of its stages are settled, cached, run, failed."""

    def __init__(self, total: int, stages: int, stream=None):
        self.stream = stream or sys.stderr
        self.total = total
        self.stages = stages
        self.rows: dict[int, dict] = {}
        self.finished = 0

    def for_variant(self, index: int, params: dict):
        reporter = self

        class Proxy:
            def update(self, state):
                reporter.update(index, params, state)

        return Proxy()

    def start(self) -> None:
        pass

    def update(self, index: int, params: dict, state) -> None:
        row = self.rows.setdefault(index, {"states": {}, "done": False})
        row["states"][state.name] = state.state
        settled = [s for s in row["states"].values() if s in ("cached", "ran", "failed", "skipped")]
        if len(settled) == self.stages and not row["done"]:
            row["done"] = True
            self.finished += 1
            counts = {k: settled.count(k) for k in ("ran", "cached", "failed", "skipped") if settled.count(k)}
            described = ", ".join(f"{k}={v}" for k, v in params.items())
            print(
                f"[{self.finished}/{self.total}] variant {index + 1} ({described}): "
                + ", ".join(f"{v} {k}" for k, v in counts.items()),
                file=self.stream,
                flush=True,
            )

    def stop(self) -> None:
        pass
