"""benchmarks/doppler_noise.py: Doppler errors at the true velocity, and EkfConfig's C/N0 law fitted to them."""
import sys
from pathlib import Path

import numpy as np
import pytest

from lfgnss.simulate import simulate_sequence

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import doppler_noise  # noqa: E402


def test_errors_at_the_true_velocity_are_the_simulated_doppler_noise():
    """Line-of-sight Dopplers of the simulator have sigma 0.1 + 2 10^(-C/N0/20) m/s: about 0.11 m/s above 45 dB-Hz."""
    seq = simulate_sequence(300, seed=3, nlos_fraction=0.0)
    cn0, error = doppler_noise.doppler_errors(seq)
    assert cn0.shape == error.shape and error.size > 0.9 * seq.prr_mask.sum() and np.all(np.isfinite(error))
    strong = 1.4826 * np.median(np.abs(error[cn0 > 45]))
    weak = 1.4826 * np.median(np.abs(error[cn0 < 30]))
    assert 0.08 < strong < 0.15 and weak > strong


def test_the_fit_recovers_the_law_it_is_given():
    centres = np.arange(22.5, 50.0, 2.5)
    sigma = doppler_noise.law_sigma_m_s(centres, 0.12, 38.0)
    bins = [{"cn0_dbhz": c, "sigma_m_s": s, "n": 100} for c, s in zip(centres, sigma)]
    fitted_sigma, fitted_ref = doppler_noise.fit_law(bins)
    assert fitted_sigma == pytest.approx(0.12, rel=1e-3) and fitted_ref == pytest.approx(38.0, abs=0.05)


def test_script_on_a_train_split(tmp_path):
    from lfgnss import datasets

    if datasets.get("hk-tst-static-2020").missing():
        pytest.skip(f"shared data missing ({datasets.get('hk-tst-static-2020').missing()[0]})")
    rows = doppler_noise.run(["hk-tst-static-2020"])
    assert len(rows) == 1 and rows[0]["split"] == "train" and rows[0]["doppler_sigma_m_s"] > 0
    bins = rows[0]["bins"]
    assert all(b["n"] >= doppler_noise.MIN_PER_BIN for b in bins) and sum(b["n"] for b in bins) <= rows[0]["n"]
    assert bins[0]["sigma_m_s"] > bins[-1]["sigma_m_s"]                 # weak signals are the noisy ones
    page = doppler_noise.markdown(rows, "cmd")
    assert "| hk-tst-static-2020 | train |" in page and "## hk-tst-static-2020 (train)" in page
    assert doppler_noise.plot(rows, tmp_path / "doppler.png").stat().st_size > 10_000
