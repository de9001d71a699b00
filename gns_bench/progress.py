"""Progress bars (steps/s, ETA) that read well in a terminal and in a log file.

In a terminal a bar redraws itself in place. Written to a file (a lane's `progress.log`, a background job's
nohup output) the same redraws are carriage returns: hours of training become one line of megabytes that
`tail` cannot show. There the bar is printed as whole lines, one every `LOG_INTERVAL_S` seconds and one at
the end.
"""
from __future__ import annotations

import re
import sys
from collections.abc import Iterable
from typing import IO, Any

from tqdm import tqdm

LOG_INTERVAL_S = 30.0  # one progress line per half minute in a log: 120 lines an hour


_CURSOR_MOVES = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")  # how tqdm places nested bars in a terminal


class _Lines:
    """A file for tqdm that writes each redraw as its own line (carriage returns, cursor moves and padding
    dropped)."""

    def __init__(self, stream: IO[str]) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        line = _CURSOR_MOVES.sub("", text.replace("\r", "")).rstrip()
        if line:
            self.stream.write(line + "\n")

    def flush(self) -> None:
        self.stream.flush()


def _is_terminal(stream: IO[str]) -> bool:
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty())


def progress_bar(iterable: Iterable[Any] | None = None, *, disable: bool = False, **kwargs: Any) -> tqdm:
    """A tqdm bar (over `iterable`, or updated by hand) on this process's stderr as it is now (a redirected
    stderr included); as lines every `LOG_INTERVAL_S` seconds when that is not a terminal."""
    stream = kwargs.pop("file", None) or sys.stderr
    if disable or _is_terminal(stream):
        return tqdm(iterable, file=stream, disable=disable, **kwargs)
    kwargs.pop("dynamic_ncols", None)  # a log has no width to follow
    return tqdm(iterable, file=_Lines(stream), mininterval=LOG_INTERVAL_S, ncols=100, **kwargs)
