"""plot_solution's figures: log-axis tick labels, a distinct style per method, the track's title."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from estimators.base import STATUS_UPDATED, Solution  # noqa: E402
from lfgnss.frames import lla_to_ecef  # noqa: E402
from lfgnss.metrics import enu_rotations  # noqa: E402
from lfgnss.outputs import plot_solution, run_styles, solution_figures  # noqa: E402


def _run(east_error_m: np.ndarray, backend: str = "ekf") -> tuple[Solution, np.ndarray]:
    """A solution whose error is ``east_error_m`` [m] east of the truth at each epoch (2D = 3D error)."""
    t = len(east_error_m)
    truth = lla_to_ecef(np.radians(52.5048 + 1e-5 * np.arange(t)), np.radians(13.375 + 1e-5 * np.arange(t)),
                        np.full(t, 40.0))
    enu = np.column_stack([east_error_m, np.zeros(t), np.zeros(t)])
    pos = truth + np.einsum("tji,tj->ti", enu_rotations(truth), enu)        # R^T enu: ENU offset -> ECEF
    sol = Solution(backend=backend, time_gps_s=1e9 + np.arange(t, dtype=float), pos_ecef_m=pos,
                   cov_ecef_m2=np.tile(np.eye(3), (t, 1, 1)), clock_m=np.zeros(t), n_used=np.full(t, 8),
                   status=np.full(t, STATUS_UPDATED))
    return sol, truth


def _labels(axis) -> list[tuple[float, str]]:
    """(tick value, label text) of the labelled ticks (major and minor) inside the view, after drawing."""
    lo, hi = sorted(axis.get_view_interval())
    out = []
    for tick in axis.get_major_ticks() + axis.get_minor_ticks():
        loc, text = tick.get_loc(), tick.label1.get_text()
        if text and lo <= loc <= hi:
            out.append((loc, text))
    return out


def _check_labels(axis, must: set[str] = frozenset()) -> list[str]:
    labels = _labels(axis)
    texts = [text for _, text in labels]
    assert len(texts) >= 2, texts
    assert len(set(texts)) == len(texts), f"duplicated tick labels: {texts}"
    assert "0.0" not in texts and "0" not in texts, texts
    for loc, text in labels:            # every label says the value at its tick
        assert float(text.replace("\N{MINUS SIGN}", "-")) == pytest.approx(loc, rel=1e-6), (loc, text)
    assert must <= set(texts), (must, texts)
    return texts


def test_log_axes_label_centimetres_to_hundreds_of_metres():
    sol, truth = _run(np.logspace(-2, 2, 60))           # 0.01 m ... 100 m
    figs = solution_figures(sol, truth)
    for fig in figs.values():
        fig.canvas.draw()
    decades = {"0.01", "0.1", "1", "10", "100"}
    _check_labels(figs["errors.png"].axes[0].yaxis, decades)
    for ax in figs["cdf.png"].axes:
        _check_labels(ax.xaxis, decades)
    assert [ax.get_xlabel() for ax in figs["cdf.png"].axes] == ["2D error [m]", "3D error [m]"]


def test_log_axes_within_one_decade_still_labelled():
    """0.2-0.9 m holds no decade: the minor ticks carry the labels, as plain decimals."""
    sol, truth = _run(np.linspace(0.2, 0.9, 40))
    figs = solution_figures(sol, truth)
    figs["errors.png"].canvas.draw()
    texts = _check_labels(figs["errors.png"].axes[0].yaxis)
    assert all(t.startswith("0.") for t in texts), texts


@pytest.mark.parametrize("n", [1, 2, 10, 11, 16, 20])
def test_run_styles_distinct_and_deterministic(n):
    names = [f"method {k}" for k in range(n)]
    styles = run_styles(names)
    assert list(styles) == names
    assert len(set(styles.values())) == n
    assert len({colour for colour, _ in styles.values()}) == n       # up to 20: the colours alone differ
    assert run_styles(names) == styles
    assert run_styles(names[:1]) == {names[0]: styles[names[0]]}       # by order, not by how many


def test_sixteen_methods_get_distinct_lines_in_every_figure(tmp_path):
    sol, truth = _run(np.logspace(-1, 1, 30), backend="LF-GNSS EKF")
    extra = {f"method {k}": _run(np.logspace(-1, 1, 30) * (k + 2))[0] for k in range(15)}
    figs = solution_figures(sol, truth, extra_solutions=extra, label="LF-GNSS EKF")
    names = ["LF-GNSS EKF", *extra]
    for fname, fig in figs.items():
        if fname == "quality.png":                  # the main run's own standard deviations and satellites only
            continue
        for ax in fig.axes:
            lines = {ln.get_label(): (tuple(ln.get_color()), ln.get_linestyle()) for ln in ax.get_lines()
                     if ln.get_label() in names}
            assert set(lines) == set(names), fname
            assert len(set(lines.values())) == len(names), fname
            assert lines == run_styles(names)
    files = plot_solution(tmp_path, sol, truth, extra_solutions=extra, label="LF-GNSS EKF")
    assert [f.name for f in files] == ["track.png", "errors.png", "cdf.png", "quality.png"]


def test_track_title_names_no_single_method_when_it_shows_several():
    sol, truth = _run(np.full(10, 2.0), backend="LF-GNSS EKF")
    other, _ = _run(np.full(10, 5.0), backend="wls")
    several = solution_figures(sol, truth, extra_solutions=[other], label="LF-GNSS EKF")
    assert several["track.png"].axes[0].get_title() == "horizontal track"
    alone = solution_figures(sol, truth, label="LF-GNSS EKF")
    assert alone["track.png"].axes[0].get_title() == "horizontal track (LF-GNSS EKF)"
    assert [several["track.png"].axes[0].get_xlabel(), several["track.png"].axes[0].get_ylabel()] == \
        ["east of the first truth point [m]", "north of the first truth point [m]"]


def test_a_static_truth_is_a_marker_on_the_track_and_a_moving_one_a_line():
    """Static truth (one point at every epoch) was drawn as a line of no length: not to be seen on the track plot."""
    sol, truth = _run(np.linspace(1.0, 5.0, 20))
    still = np.broadcast_to(truth[0], truth.shape).copy()
    for points, marker, linestyle, n in ((still, "*", "None", 1), (truth, "None", "-", 20)):
        line = next(ln for ln in solution_figures(sol, points)["track.png"].axes[0].get_lines()
                    if ln.get_label() == "truth")
        assert (line.get_marker(), line.get_linestyle(), len(line.get_xdata())) == (marker, linestyle, n)


def test_a_figure_that_cannot_be_written_costs_that_figure_only(tmp_path):
    """A folder where errors.png goes: track.png and cdf.png are still written, then the error names errors.png."""
    sol, truth = _run(np.linspace(1.0, 5.0, 20))
    (tmp_path / "errors.png" / "inside").mkdir(parents=True)
    with pytest.raises(OSError) as info:
        plot_solution(tmp_path, sol, truth)
    assert info.value.filename == str(tmp_path / "errors.png")
    for name in ("track.png", "cdf.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cdf.png", "errors.png", "quality.png",
                                                          "track.png"]                          # no temporary


def test_save_figure_writes_the_format_its_suffix_names(tmp_path):
    from lfgnss.outputs import save_figure

    sol, truth = _run(np.linspace(1.0, 5.0, 20))
    fig = solution_figures(sol, truth)["track.png"]
    from lfgnss.outputs import FIGURES, TRUTH_FIGURES

    assert tuple(solution_figures(sol, truth)) == TRUTH_FIGURES and tuple(solution_figures(sol)) == FIGURES
    for name, magic in (("t.pdf", b"%PDF"), ("t.png", b"\x89PNG"), ("t", b"\x89PNG")):
        save_figure(tmp_path / name, fig)
        assert (tmp_path / name).read_bytes()[:4] == magic, name


def test_every_figure_is_titled_the_main_run_stands_out_and_the_cdf_legend_covers_no_panel():
    """Review (session 50): no figure named its data; the LF-GNSS EKF was one of 16 thin curves; the CDF legend sat
    between the panels."""
    runs = [_run(np.full(10, v), backend=f"run{v:g}") for v in (1.0, 2.0, 3.0, 4.0, 5.0)]
    (main, truth), others = runs[0], [sol for sol, _ in runs[1:]]
    figures = solution_figures(main, truth, extra_solutions=others, label="LF-GNSS EKF", title="my-drive, test split")
    assert {name: fig.get_suptitle() for name, fig in figures.items()} == dict.fromkeys(figures, "my-drive, test split")
    for name, fig in figures.items():
        if name == "quality.png":                   # the main run's alone
            continue
        lines = [ln for ax in fig.axes for ln in ax.get_lines() if ln.get_label() in ("LF-GNSS EKF", "run2")]
        widths = {ln.get_label(): ln.get_linewidth() for ln in lines}
        assert widths["LF-GNSS EKF"] == 2 * widths["run2"], widths
    left, right = figures["cdf.png"].axes
    assert left.get_legend() is None and right.get_legend() is not None
    assert solution_figures(main, truth)["cdf.png"].get_suptitle() == ""            # no title given: none drawn


def test_the_benchmark_titles_its_figures_with_the_dataset_and_split(monkeypatch, tmp_path):
    import lfgnss.outputs
    from lfgnss import benchmark

    seen = {}
    monkeypatch.setattr(lfgnss.outputs, "plot_solution", lambda *a, title=None, **k: seen.update(title=title))
    sol, truth = _run(np.full(5, 1.0))
    benchmark._plot(tmp_path, "my-drive", {"LF-GNSS EKF": sol}, truth, None)
    assert seen["title"] == "my-drive, test split (python -m lfgnss.benchmark)"


def test_quality_figure_shows_the_solutions_own_sds_satellites_and_status_without_truth():
    """A run without truth (the usual case with one's own data) had no plot and no account of itself: quality.png
    draws the standard deviations and satellites against GPST, and marks coasted, reset and unsolved epochs."""
    from dataclasses import replace

    from estimators.base import STATUS_COASTED, STATUS_NONE, STATUS_RESET
    from lfgnss.solve import solution_words

    sol, _ = _run(np.full(6, 1.0))
    cov = np.tile(np.diag([4.0, 9.0, 16.0]), (6, 1, 1))       # ECEF; at 52.5 N the ENU sds mix them
    sol = replace(sol, cov_ecef_m2=cov, n_used=np.array([8, 7, 0, 9, 9, 0]),
                  status=np.array([STATUS_RESET, STATUS_UPDATED, STATUS_COASTED, STATUS_UPDATED, STATUS_UPDATED,
                                   STATUS_NONE]))
    fig = solution_figures(sol)["quality.png"]
    ax_sd, ax_n = fig.axes
    sd = {ln.get_label(): ln.get_ydata() for ln in ax_sd.get_lines()}
    np.testing.assert_allclose(np.column_stack([sd["east"], sd["north"], sd["up"]]), sol.sd_enu_m(), rtol=0)
    marks = {ln.get_label(): (list(ln.get_xdata()), list(ln.get_ydata())) for ln in ax_n.get_lines()}
    assert marks["reset (1)"] == ([0.0], [8.0]) and marks["coasted (1)"] == ([2.0], [0.0])      # at their satellites
    assert marks["no position (1)"] == ([5.0], [0.0])
    used = next(ln for ln in ax_n.get_lines() if ln.get_label() == "satellites used")
    np.testing.assert_array_equal(used.get_ydata(), [8, 7, 0, 9, 9, np.nan])
    assert ax_n.get_xlabel() == "time since 2011-09-14 01:46:40.0 GPST [s]"
    sd_med = np.median(sol.sd_enu_m()[:5], axis=0)
    assert solution_words(sol) == (f"solution: 5 of 6 epochs with a position (updated 3, coasted 1, reset 1); median "
                                   f"standard deviation east / north / up {sd_med[0]:.2f} / {sd_med[1]:.2f} / "
                                   f"{sd_med[2]:.2f} m; median 8 satellites used")
