"""The match stage's progress bar: pairs done, pairs per minute, time left."""

from __future__ import annotations

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text


class RateColumn(ProgressColumn):
    """Pairs per minute (rich has a speed column for bytes only)."""

    def render(self, task) -> Text:
        speed = task.finished_speed or task.speed
        return Text("-- pairs/min" if speed is None else f"{speed * 60:.1f} pairs/min", style="cyan")


def progress_bar(console: Console) -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), RateColumn(),
        TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), console=console,
    )
