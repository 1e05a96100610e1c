"""benchmarks/page.py: how the benchmark scripts publish their page and figure."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import page  # noqa: E402


def test_publish_prints_and_only_with_write_writes(tmp_path, capsys):
    doc, figure = tmp_path / "x.md", tmp_path / "figures" / "x.png"
    assert page.publish("# page", doc, False, figure, lambda path: path) == 0
    assert capsys.readouterr().out == "# page\n" and not doc.exists()

    def draw(path):
        path.parent.mkdir()
        path.write_bytes(b"png")
        return path

    assert page.publish("# page", doc, True, figure, draw) == 0
    assert doc.read_text() == "# page" and figure.read_bytes() == b"png"
    assert capsys.readouterr().out.endswith(f"written: {doc}, {figure}\n")


def test_a_run_without_a_figure_removes_the_one_an_earlier_run_left(tmp_path, capsys):
    """The page of a run that draws nothing names no figure, so the old one must not stay beside it."""
    doc, figure = tmp_path / "x.md", tmp_path / "x.png"
    figure.write_bytes(b"old")
    page.publish("# page", doc, True, figure, None)
    assert not figure.exists() and doc.read_text() == "# page"
    assert f"removed {figure} (this run draws none)" in capsys.readouterr().out
    page.publish("# page", doc, True, figure, None)                 # nothing left to remove: says only the page
    assert capsys.readouterr().out.endswith(f"written: {doc}\n")


def test_a_figure_to_draw_without_its_path_is_refused(tmp_path):
    with pytest.raises(ValueError, match="needs its path"):
        page.publish("# page", tmp_path / "x.md", True, None, lambda path: path)


def test_parse_refuses_an_unknown_dataset_in_one_line(capsys):
    p = page.script_parser("A script.\n\nMore.", "write it")
    assert page.parse(p, ["--datasets", "nope"], "x.py") is None
    assert capsys.readouterr().err.startswith("x.py: unknown dataset nope; known: ")
    assert page.parse(p, ["--datasets", "berlin-pp", "--write"], "x.py").write
    assert page.parse(page.script_parser("A script.", "write it", ("berlin-pp",)), [], "x.py").datasets == ["berlin-pp"]


def test_splits_given_to_the_parser_are_its_default_and_its_only_choices(capsys):
    p = page.script_parser("A script.", "write it", splits=("train", "val"))
    assert page.parse(p, [], "x.py").splits == ["train", "val"]
    assert page.parse(p, ["--splits", "val"], "x.py").splits == ["val"]
    with pytest.raises(SystemExit):
        page.parse(p, ["--splits", "test"], "x.py")
    assert "invalid choice: 'test'" in capsys.readouterr().err
    assert not hasattr(page.parse(page.script_parser("A script.", "write it"), [], "x.py"), "splits")
