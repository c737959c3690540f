"""Progress lines show items, failures, rate and ETA."""

import io

from anchordp3.pipeline.progress import Progress


def test_progress_reports_done_failed_rate_and_eta():
    buf = io.StringIO()
    p = Progress("rollout", 3, stream=buf, interval=0.0)
    p.update(True)
    p.update(False)
    p.update(True)
    last = buf.getvalue().strip().splitlines()[-1]
    assert "3/3 items" in last and "1 failed" in last and "items/s" in last and "ETA" in last
