"""The quick tier's list: measured durations in, the most expensive tests out until the rest fits the budget."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from tiers import costs, slow_tests  # noqa: E402

REPORT = """
============================= slowest durations =============================
12.50s call     tests/test_a.py::test_big[x]
2.50s call     tests/test_a.py::test_big[y]
3.00s setup    tests/test_b.py::test_fixture_heavy
1.00s call     tests/test_b.py::test_fixture_heavy
0.40s call     tests/test_b.py::test_small
0.01s teardown tests/test_b.py::test_small
"""


def test_costs_add_a_test_s_cases_and_its_setup():
    c = costs(REPORT)
    assert c == pytest.approx({"tests/test_a.py::test_big": 15.0, "tests/test_b.py::test_fixture_heavy": 4.0,
                               "tests/test_b.py::test_small": 0.41})


def test_the_most_expensive_go_until_the_rest_fits():
    c = costs(REPORT)
    assert slow_tests(c, budget=5.0) == ["tests/test_a.py::test_big"]
    assert slow_tests(c, budget=1.0) == ["tests/test_a.py::test_big", "tests/test_b.py::test_fixture_heavy"]
    assert slow_tests(c, budget=100.0) == []


def test_every_listed_slow_test_exists():
    """A renamed test would silently join the quick tier: every line of slow.txt names a test in its file."""
    here = Path(__file__).parent
    for line in (here / "slow.txt").read_text().splitlines():
        node = line.split("#")[0].strip()
        if node:
            path, name = node.split("::")
            assert f"def {name}(" in (here.parent / path).read_text(), node


def test_adding_to_the_list_keeps_it_and_fits_the_rest(tmp_path, monkeypatch):
    """``--add``: the listed tests stay, the most expensive of the others join until the rest fits the budget."""
    import tiers

    here = tmp_path / "tests"
    here.mkdir()
    (here / "slow.txt").write_text("# head\ntests/test_old.py::test_kept  # 3.0 s\n"
                                   "tests/test_old.py::test_noted  # compiling: a note written by hand\n")
    (tmp_path / "d.txt").write_text(REPORT)
    monkeypatch.setattr(tiers, "__file__", str(here / "tiers.py"))
    monkeypatch.setattr(sys, "argv", ["tiers.py", str(tmp_path / "d.txt"), "--add", "--budget", "5"])
    assert tiers.main() == 0
    listed = tiers.read_list(here / "slow.txt")
    assert listed == pytest.approx({"tests/test_old.py::test_kept": 3.0, "tests/test_old.py::test_noted": 0.0,
                                    "tests/test_a.py::test_big": 15.0})
    text = (here / "slow.txt").read_text()
    assert "test_big  # 15.0 s compiling" in text and "test_noted  # compiling: a note written by hand" in text
