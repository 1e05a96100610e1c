"""benchmarks/front_end.py --table, which writes docs/front_end.md, runs on the shared data (session 49 broke it)."""
from __future__ import annotations

from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def test_the_front_end_table_is_made(shared_data, rnx2rtkp, capsys, monkeypatch):
    for folder in ("urbannav-hk-tst-20190428", "smartloc-berlin-potsdamer-platz-rinex", "hk-tst-static-20200603"):
        shared_data(folder)
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import front_end

    assert front_end.main(["--table", "--no-doc"]) == 0
    out = capsys.readouterr().out
    assert "| dataset | vs | subset | n | d2_p50 | d2_p95 | d3_p50 | d3_p95 | ratio_p50 |" in out
    assert "| hk-tst-static-2020 | RTKLIB benchmark | both solve |" in out
