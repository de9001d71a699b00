"""Progress bars in a log file come as whole lines; in a terminal they redraw in place."""
from __future__ import annotations

import io

from gns_bench import progress
from gns_bench.progress import progress_bar


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _run(stream: io.StringIO, steps: int = 10) -> str:
    bar = progress_bar(total=steps, file=stream, desc="train", unit="step")
    for _ in range(steps):
        bar.update(1)
    bar.close()
    return stream.getvalue()


def test_a_log_gets_one_line_per_redraw_and_the_final_count(monkeypatch):
    monkeypatch.setattr(progress, "LOG_INTERVAL_S", 0.0)  # every update redraws
    text = _run(io.StringIO())
    lines = text.splitlines()
    assert "\r" not in text
    assert len(lines) >= 10  # the redraws, each its own line, not one line of carriage returns
    assert all(line == line.rstrip() and line.startswith("train:") for line in lines)
    assert "10/10" in lines[-1]


def test_a_nested_bar_in_a_log_moves_no_cursor(monkeypatch):
    monkeypatch.setattr(progress, "LOG_INTERVAL_S", 0.0)
    stream = io.StringIO()
    outer = progress_bar(total=2, file=stream, desc="evaluate")
    inner = progress_bar(total=3, file=stream, desc="rollout", leave=False)  # placed below the outer one
    for _ in range(3):
        inner.update(1)
    inner.close()
    outer.update(2)
    outer.close()
    assert "\x1b" not in stream.getvalue() and "rollout:" in stream.getvalue()


def test_a_log_is_throttled_to_the_interval():
    text = _run(io.StringIO(), steps=1000)  # 1,000 fast updates inside one interval
    assert len(text.splitlines()) <= 3  # the first draw and the last, not a thousand


def test_a_terminal_redraws_in_place():
    assert "\r" in _run(_Terminal())


def test_an_iterable_is_wrapped_and_a_disabled_bar_writes_nothing():
    stream = io.StringIO()
    assert list(progress_bar(range(3), file=stream)) == [0, 1, 2]
    quiet = io.StringIO()
    assert list(progress_bar(range(3), file=quiet, disable=True)) == [0, 1, 2]
    assert quiet.getvalue() == ""
