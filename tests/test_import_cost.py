"""What importing the package and building the command line load: the heavy libraries only where a run needs them
(filterpy, and through it scipy.stats, half a second, only when an EKF solves; gtsam only for the graph; torch only
for learning)."""
import subprocess
import sys

HEAVY = ("filterpy", "scipy", "gtsam", "torch")


def _loaded_after(code: str) -> list[str]:
    """The HEAVY modules a fresh interpreter holds after running ``code``."""
    probe = f"{code}\nimport sys\nprint(' '.join(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return out.stdout.split()


def test_the_estimators_package_and_the_command_line_load_no_heavy_library():
    assert _loaded_after("import estimators, lfgnss.solve\nlfgnss.solve.build_parser()") == []


def test_an_ekf_loads_filterpy_when_built_so_a_timed_solve_does_not_count_it():
    assert _loaded_after("import estimators\nestimators.create('plain-ekf')") == ["filterpy", "scipy"]
    code = ("import estimators\nfrom lfgnss.simulate import simulate_sequence\n"
            "estimators.create('plain-ekf').solve(simulate_sequence(5, seed=1))")
    assert _loaded_after(code) == ["filterpy", "scipy"]                   # and nothing else it does not use
