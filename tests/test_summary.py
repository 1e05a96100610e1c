"""Feature summary command: statistics and plots for a dataset (here the bundled sample as a user dataset)."""
import numpy as np

from lfgnss import datasets
from lfgnss.solve import SAMPLE_DIR
from lfgnss.summary import feature_statistics, main


def test_summary_command_writes_stats_and_plots(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    cfg = tmp_path / "sample.toml"
    cfg.write_text(f'''
id = "summary-sample"
obs = ["{SAMPLE_DIR / 'Berlin_Potsdamer_Platz.obs.gz'}"]
nav = ["{SAMPLE_DIR / 'brdc1580.16n.gz'}", "{SAMPLE_DIR / 'brdc1580.16g.gz'}"]
[truth]
file = "{SAMPLE_DIR / 'Berlin_Potsdamer_Platz_GT.txt'}"
format = "smartloc"
time_origin_gps_s = {1900 * 604800 + 126641.7}
''')
    assert main(["--register", str(cfg), "--out", str(tmp_path / "png")]) == 0
    out = capsys.readouterr().out
    assert "summary-sample" in out and "cn0_p50_dbhz" in out
    pngs = sorted(p.name for p in (tmp_path / "png").glob("*.png"))
    assert pngs == ["summary-sample-cn0_residual.png", "summary-sample-skyplot.png"]
    rows = feature_statistics(datasets.build("summary-sample"))
    assert [r["system"] for r in rows] == ["all", "G", "R"]
    assert 10 < rows[0]["sats_per_epoch"] < 20 and 30 < rows[0]["cn0_p50_dbhz"] < 50
    assert np.isclose(rows[1]["sats_per_epoch"] + rows[2]["sats_per_epoch"], rows[0]["sats_per_epoch"])


def test_summary_bad_input_is_one_line_and_a_dataset_counts_once(tmp_path, capsys, sample_toml):
    """Each of these used to end in a traceback (exit 1), a missing obs file in 'no dataset found' (exit 0), and a
    dataset named and registered too was summarised and plotted twice."""
    def one_error() -> str:
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err, err
        return err.rstrip("\n")

    assert main(["nosuch", "--out", str(tmp_path / "o")]) == 2
    assert one_error().startswith("error: unknown dataset 'nosuch'; known: ")
    assert main(["--register", str(tmp_path / "none.toml")]) == 2
    assert one_error().startswith(f"error: {tmp_path / 'none.toml'}: unreadable dataset config")
    toml = sample_toml("gone-drive")
    toml.write_text(toml.read_text().replace("Berlin_Potsdamer_Platz.obs.gz", "missing.obs"))
    assert main(["--register", str(toml), "--out", str(tmp_path / "o")]) == 2
    assert one_error().startswith("error: dataset not built: gone-drive: missing ")
    (tmp_path / "a-file").write_text("x")
    assert main(["--register", str(sample_toml("twice")), "--out", str(tmp_path / "a-file")]) == 2
    assert one_error() == f"error: {tmp_path / 'a-file'}: --out is a file, not a folder"
    assert main(["twice", "--register", str(sample_toml("twice")), "--out", str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out
    assert out.count("twice ") == 3 and out.count("twice-skyplot.png") == 1       # all, G, R rows; one plot each
