"""The progress bar: counts, the final state, and log lines that do not run on after the bar."""

import io
import logging

from mvrecon.progress import Bar, clear_line


def test_bar_counts_an_iterable_and_erases_itself_at_the_end():
    out = io.StringIO()
    bar = Bar(range(5), desc="features", unit="image", stream=out, min_interval=0)
    assert list(bar) == [0, 1, 2, 3, 4]
    draws = out.getvalue().split("\r")
    last_draw = draws[-3]  # then the blanking and the final carriage return: the loop's end closed the bar
    assert last_draw.startswith("features: 100% |") and " 5/5 [" in last_draw and "image/s" in last_draw
    assert draws[-2:] == [" " * len(last_draw.rstrip()), ""]


def test_a_log_record_clears_the_bar_first():
    out = io.StringIO()
    handler = logging.StreamHandler(out)
    handler.addFilter(clear_line)
    log = logging.getLogger("mvrecon.test_progress")
    log.addHandler(handler)
    log.propagate = False
    try:
        bar = Bar(total=4, desc="mapping", unit="img", stream=out, min_interval=0)
        bar.update(1)
        drawn = out.getvalue()
        log.warning("image 3: too few matches")
        # the bar's text is blanked and the cursor back at the line start before the message
        assert out.getvalue() == drawn + "\r" + " " * (len(drawn) - 1) + "\r" + "image 3: too few matches\n"
        bar.update(3)
        assert out.getvalue().split("\r")[-1].startswith("mapping: 100% |") and "4/4" in out.getvalue()
        bar.close()
    finally:
        log.removeHandler(handler)
