"""Writes the notebooks of this folder (python notebooks/make_notebooks.py from the repo root)."""
import nbformat as nbf
from pathlib import Path

def nb(cells, path):
    n = nbf.v4.new_notebook()
    n.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    n.cells = [nbf.v4.new_markdown_cell(c[1]) if c[0] == "md" else nbf.v4.new_code_cell(c[1]) for c in cells]
    for k, cell in enumerate(n.cells):
        cell.id = f"cell-{k}"       # not nbformat's random ids: a rerun rewrites only what changed
    nbf.write(n, path)

nb([
("md", "# Comparing estimators\n\nEqual-weight least squares, the plain EKF (hand-set C/N0 noise, innovation gate), and the LF-GNSS EKF (forward, and smoothed backwards with `smooth=True` for post-processing) and factor graph with the shipped model, on the bundled Berlin drive (smartLoc, CC BY-SA 4.0) and, when present, on a shared benchmark dataset's test split.\n\nThe bundled drive is berlin-pp's own drive, so the shipped model was trained on 724 of its epochs, with 148 more in its validation split: its rows on it are partly in-sample, a demonstration of the API, not a result (the shared dataset's test split below is out of sample; `python -m lfgnss.benchmark` gives the results)."),
("code", """import tempfile, warnings
from pathlib import Path
warnings.simplefilter("ignore", FutureWarning)
from IPython.display import Image, display

import lfgnss
import estimators
from lfgnss import datasets
from lfgnss.metrics import accuracy_table, format_markdown
from lfgnss.outputs import plot_solution
from lfgnss.solve import DEFAULT_MODEL, SAMPLE_NAV, SAMPLE_OBS, SAMPLE_TRUTH

folder = Path(tempfile.mkdtemp())      # figures go here, not into the notebook's folder"""),
("code", """meas = lfgnss.load(SAMPLE_OBS, SAMPLE_NAV)
fix = lfgnss.spp(meas)
truth = datasets.read_truth(SAMPLE_TRUTH, meas.time_gps_s, "smartloc")   # (T, 3) ECEF [m], NaN where none
seq = lfgnss.build_sequence(meas, fix, truth_ecef_m=truth)
print(fix.summary())"""),
("code", """def learned():
    if DEFAULT_MODEL.exists():
        from learning.export import load_model
        return {"noise": load_model(DEFAULT_MODEL)}
    return {}

def compare(seq):
    runs = {"least squares": estimators.create("wls"), "plain EKF": estimators.create("plain-ekf"),
            "LF-GNSS EKF": estimators.create("ekf", **learned()),
            "LF-GNSS EKF + RTS smoother": estimators.create("ekf", smooth=True, **learned()),
            "LF-GNSS FGO": estimators.create("fgo", **learned())}
    sols = {name: est.solve(seq) for name, est in runs.items()}
    rows = [accuracy_table(s.pos_ecef_m, seq.truth_ecef_m, s.available, method=name) for name, s in sols.items()]
    return sols, rows

sols, rows = compare(seq)     # the batch graph may warn that Levenberg-Marquardt stopped at max_iterations: its
                              # positions are then its last iterate (docs/fgo_convergence.md)
print(format_markdown(rows, columns=["method", "availability", "rmse_2d_m", "rmse_3d_m", "p95_3d_m"]))"""),
("code", """# plot_solution draws every run against the truth (track, error against time, error CDF over the labelled
# epochs, so that a curve ends at the estimator's availability); the CDFs:
others = {name: s for name, s in sols.items() if name != "LF-GNSS EKF"}
plot_solution(folder, sols["LF-GNSS EKF"], seq.truth_ecef_m, extra_solutions=others, prefix="berlin-",
              label="LF-GNSS EKF")
display(Image(filename=str(folder / "berlin-cdf.png")))"""),
("md", "## A shared benchmark dataset (skipped when the shared data are absent: `$LFGNSS_SHARED_DATA`, else `../shared/data` beside the checkout)"),
("code", """spec = datasets.get("hk-tst-static-2020")
if spec.missing():
    print("shared data not found:", spec.missing()[0])
else:
    test = datasets.load_split("hk-tst-static-2020", "test")[0]
    _, rows = compare(test)
    print(format_markdown(rows, columns=["method", "availability", "rmse_2d_m", "rmse_3d_m"]))"""),
], "notebooks/estimator_comparison.ipynb")

nb([
("md", "# Training walk-through\n\nThe LF-GNSS network is trained end to end through a differentiable EKF (`learning.torch_ekf`). This notebook trains a small model for a few epochs on simulated urban drives (seconds on a laptop), exports it to a model file and uses it in the filterpy EKF plug-in. For the real benchmark data use `python -m learning.train --config shipped` (`lfgnss/data/model/README.md` gives the command and configuration behind each shipped model)."),
("code", """import tempfile, warnings
from pathlib import Path
warnings.simplefilter("ignore", FutureWarning)
from IPython.display import Image, display
from learning.train import load_config, train
from learning.export import load_model
import estimators
from lfgnss.simulate import simulate_sequence
from lfgnss.metrics import accuracy_table"""),
("code", """# simulated drives, as learning/configs/synthetic.toml, but shorter (120 epochs, 20-epoch windows, 3 training
# epochs) so the notebook runs in seconds; spelled out so it runs from any folder
config = load_config(None, ['data.datasets=["synthetic"]', "train.epochs=3", "data.synthetic.n_epochs=120",
                            "data.window=20"])
print({k: config[k] for k in ("data", "loss")})"""),
("code", """out = Path(tempfile.mkdtemp()) / "run"
result = train(config, out, progress=False)

# the run's training curves, which learning.train draws from its log.csv (one row per epoch; epoch 0 scores the
# untrained model, so it has no training loss)
display(Image(filename=str(out / "curves.png")))"""),
("md", "Three epochs on two short simulated drives only show the mechanics: expect this model to lose to the plain EKF below. The shipped models train for 30-120 epochs on real drives, and cross-validation (next section) is how to tell whether a recipe helps."),
("code", """model = load_model(out / "model.npz")
print(model, model.metadata["val_rmse_3d_m"])
seq = simulate_sequence(200, seed=42)
for name, est in {"plain EKF": estimators.create("plain-ekf"), "learned EKF": estimators.create("ekf", noise=model)}.items():
    sol = est.solve(seq)
    print(name, round(accuracy_table(sol.pos_ecef_m, seq.truth_ecef_m, sol.available)["rmse_3d_m"], 2), "m")"""),
("md", "## Does the recipe generalise?\n\nA short validation split is one street. `learning.crossval` cuts the train + validation epochs into contiguous blocks, trains on all but one and scores the held-out block next to the plain EKF (`python -m learning.crossval --config ... --folds 3`). \"last\" is the honest figure for a fixed schedule; \"best\" is picked on the held-out block itself. On the real data this showed that the learned EKF generalises on berlin-pp and the static set, and on hk-tst-2019 only fine-tuned from a berlin + static model (better than the plain EKF on two blocks of three; from scratch its 240 train epochs are too few) (`lfgnss/data/model/README.md`)."),
("code", """from learning.crossval import crossval
rows = crossval(config, 2, Path(tempfile.mkdtemp()) / "cv", progress=False)
for r in rows:
    print(r["fold"], "plain EKF", round(r["plain_ekf_rmse_3d_m"], 2), "m | learned, last epoch", round(r["last_rmse_3d_m"], 2), "m")"""),
], "notebooks/training_walkthrough.ipynb")

nb([
("md", "# Use your own data\n\nDescribe your receiver's files in a small TOML file, register it, and every tool of lfgnss (the estimators, the trainer, the benchmark) can use it by id. Here the bundled Berlin files stand in for your own. (To position a drive, `python -m lfgnss.solve --obs ROVER.obs --nav BRDC.nav` needs no TOML, and `--obs` takes several files of one receiver; a TOML is for training, cross-validation and the benchmark, and lists several obs files the same way.)"),
("code", """import tempfile, warnings
from pathlib import Path
warnings.simplefilter("ignore", FutureWarning)
import estimators
from lfgnss import datasets
from lfgnss.metrics import accuracy_table, format_text
from lfgnss.outputs import plot_solution, write_csv, write_pos
from lfgnss.solve import SAMPLE_DIR
from IPython.display import Image, display

folder = Path(tempfile.mkdtemp())
config = folder / "my-drive.toml"
config.write_text(f'''
id = "my-drive"
obs = ["{SAMPLE_DIR / 'Berlin_Potsdamer_Platz.obs.gz'}"]
nav = ["{SAMPLE_DIR / 'brdc1580.16n.gz'}", "{SAMPLE_DIR / 'brdc1580.16g.gz'}"]
[truth]
file = "{SAMPLE_DIR / 'Berlin_Potsdamer_Platz_GT.txt'}"
format = "smartloc"
time_origin_gps_s = {1900 * 604800 + 126641.7}
[splits]
axis = "relative_s"
train = [0, 150]
val = [150, 180]
test = [180, 400]
''')
spec = datasets.register_toml(config)
print(spec.id, [p.name for p in spec.files()])"""),
("code", """print(datasets.alignment_report(["my-drive"]))"""),
("code", """test = datasets.load_split("my-drive", "test")[0]
sol = estimators.create("plain-ekf").solve(test)
print(format_text([accuracy_table(sol.pos_ecef_m, test.truth_ecef_m, sol.available, method="plain-ekf")]))
print(write_pos(folder / "my-drive.pos", sol), write_csv(folder / "my-drive.csv", sol, test.truth_ecef_m))
# the CSV's columns, as a pandas table: times (GPST, UTC), ECEF and WGS84 position, ENU standard deviations and
# velocity, receiver clock, satellites used, status (updated / coasted / reset / none), errors against the truth
sol.to_frame(test.truth_ecef_m).head()"""),
("md", "`plot_solution` writes the track, the error against time, the error CDF and `quality.png` as PNG files (here into the temporary folder). The quality plot is what the solution says of itself, truth or not: its standard deviations east, north and up, and the satellites it used, with coasted (prediction only), reset (restarted from the least-squares fix) and unsolved epochs marked. The error against time, then the quality plot:"),
("code", """figures = plot_solution(folder / "figures", sol, test.truth_ecef_m, prefix="my-drive-", label="plain EKF")
print([f.name for f in figures])
display(Image(filename=str(folder / "figures" / "my-drive-errors.png")))
display(Image(filename=str(folder / "figures" / "my-drive-quality.png")))"""),
("md", "## Fine-tune the shipped model on your drive\n\nWith a few minutes of labelled data, start from the shipped model rather than from scratch: `train.init` loads its weights, network, features, normalisation and filter (the `[ekf]` keys you set win), and the new model file records what it started from. `data.register` names your dataset TOML files. One epoch here, to keep the notebook quick (the bundled drive is also one the shipped model was trained on, so this shows the mechanics, not a gain). The same from the shell:\n\n    python -m learning.train --config finetune --set 'data.register=[\"my-drive.toml\"]' --set 'data.datasets=[\"my-drive\"]' --out runs/my-drive\n\n`python -m lfgnss.datasets --register my-drive.toml` prints the alignment report."),
("code", """from learning.export import load_model
from learning.train import load_config, train
from lfgnss.solve import DEFAULT_MODEL

cfg = load_config(None, [f'data.register=["{config}"]', 'data.datasets=["my-drive"]', f'train.init="{DEFAULT_MODEL}"',
                         "train.epochs=1", "data.window=100", "data.stride=20", "train.lr=1e-3", 'train.select="last"'])
train(cfg, folder / "fine-tuned", progress=False)
tuned = load_model(folder / "fine-tuned" / "model.npz")
print("started from", tuned.metadata["init_model"]["path"], "trained on", tuned.metadata["init_model"]["datasets"])
for name, noise in {"shipped model": load_model(DEFAULT_MODEL), "fine-tuned": tuned}.items():
    sol = estimators.create("ekf", noise=noise).solve(test)
    print(name, round(accuracy_table(sol.pos_ecef_m, test.truth_ecef_m, sol.available)["rmse_3d_m"], 2), "m 3D")"""),
], "notebooks/your_own_data.ipynb")
