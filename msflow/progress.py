"""Progress display: per-stage state (cached / running / done / failed / skipped) and time.

On a terminal a live rich table; otherwise one line per state change (logs, CI). Both write to stderr.
"""

from __future__ import annotations

import sys
import time
from typing import TYPE_CHECKING, Any, TextIO

from msflow.jobs import StageStatus

if TYPE_CHECKING:
    from msflow.runner import Reporter, StageState

STYLE = {
    StageStatus.PENDING: ("·", "dim"),
    StageStatus.CACHED: ("=", "cyan"),
    StageStatus.RUNNING: ("…", "yellow"),
    StageStatus.RAN: ("✓", "green"),
    StageStatus.FAILED: ("✗", "bold red"),
    StageStatus.SKIPPED: ("-", "dim"),
}
LABEL = {StageStatus.RAN: "done"}


class PlainReporter:
    def __init__(self, names: list[str], stream: TextIO | None = None):
        self.stream = stream or sys.stderr
        self.width = max((len(n) for n in names), default=8)

    def start(self) -> None:
        pass

    def update(self, state: StageState) -> None:
        if state.state is StageStatus.PENDING:
            return
        mark, _ = STYLE.get(state.state, ("?", ""))
        timing = (
            f"{state.seconds:7.2f}s" if state.state in (StageStatus.RAN, StageStatus.FAILED) and state.seconds else ""
        )
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

        self.rows: dict[str, list[Any]] = {n: [StageStatus.PENDING, 0.0, "", None] for n in names}
        self.console = Console(stderr=True)
        self.live = Live(self, console=self.console, refresh_per_second=8, transient=False)

    def __rich__(self) -> Any:
        from rich.table import Table

        table = Table.grid(padding=(0, 2))
        for name, (state, seconds, detail, since) in self.rows.items():
            mark, style = STYLE.get(state, ("?", ""))
            if state is StageStatus.RUNNING and since is not None:
                seconds = time.perf_counter() - since
            timing = f"{seconds:.2f}s" if state in (StageStatus.RUNNING, StageStatus.RAN, StageStatus.FAILED) else ""
            table.add_row(
                f"[{style}]{mark}[/]", name, f"[{style}]{LABEL.get(state, state)}[/]", timing, f"[dim]{detail}[/]"
            )
        return table

    def start(self) -> None:
        self.live.start()

    def update(self, state: StageState) -> None:
        row = self.rows.setdefault(state.name, [StageStatus.PENDING, 0.0, "", None])
        row[0], row[1], row[2] = state.state, state.seconds, state.detail
        if state.state is StageStatus.RUNNING:
            row[3] = time.perf_counter()

    def stop(self) -> None:
        self.live.stop()


def make_reporter(names: list[str], quiet: bool = False) -> PlainReporter | RichReporter | None:
    if quiet:
        return None
    if sys.stderr.isatty():
        return RichReporter(names)
    return PlainReporter(names)


class SweepReporter:
    """One line per variant: how many of its stages are settled, cached, run, failed."""

    def __init__(self, total: int, stream: TextIO | None = None):
        self.stream = stream or sys.stderr
        self.total = total
        self.rows: dict[int, dict[str, Any]] = {}
        self.finished = 0

    def for_variant(self, index: int, params: dict[str, Any], stages: int) -> Reporter:
        """The reporter of variant ``index``, whose pipeline (loaded with the variant's overrides, ``vars.*``
        included) has ``stages`` stages."""
        reporter = self
        self.rows[index] = {"states": {}, "done": False, "stages": stages}

        class Proxy:
            def update(self, state: StageState) -> None:
                reporter.update(index, params, state)

        return Proxy()

    def start(self) -> None:
        pass

    def update(self, index: int, params: dict[str, Any], state: StageState) -> None:
        row = self.rows[index]
        row["states"][state.name] = state.state
        settled = [s for s in row["states"].values() if s.settled]
        if len(settled) == row["stages"] and not row["done"]:
            row["done"] = True
            self.finished += 1
            order = (StageStatus.RAN, StageStatus.CACHED, StageStatus.FAILED, StageStatus.SKIPPED)
            counts = {k.value: settled.count(k) for k in order if settled.count(k)}
            described = ", ".join(f"{k}={v}" for k, v in params.items())
            print(
                f"[{self.finished}/{self.total}] variant {index + 1} ({described}): "
                + ", ".join(f"{v} {k}" for k, v in counts.items()),
                file=self.stream,
                flush=True,
            )

    def stop(self) -> None:
        pass
