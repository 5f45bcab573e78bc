"""Rewrite ``tests/slow.txt``, the tests left out of the quick tier, from measured durations.

    python -m pytest -q --durations=0 > durations.txt      # a full run
    python tests/tiers.py durations.txt [--budget 150]

    # a run of the quick tier on a machine that has compiled nothing (XDG_CACHE_HOME set to a new folder)
    python -m pytest -q -m "not slow" --durations=0 > cold.txt
    python tests/tiers.py cold.txt --add --budget 850

Each test (its node id without parameters: all its cases together) costs the sum of its cases' setup and call
times. The most expensive tests are listed as slow until the rest, the quick tier, costs at most ``--budget``
seconds of worker time (two workers share it: about half of that in wall time, plus start-up). Tests marked
``@pytest.mark.slow`` in their file stay slow whatever this list says.

With ``--add`` the list is kept and the most expensive tests of the durations given (a quick-tier run, e.g. on a
machine that has compiled nothing, where compilation dominates) join it until the rest fits the budget.
"""
from __future__ import annotations

import argparse
import re
from collections import defaultdict
from pathlib import Path

LINE = re.compile(r"^\s*([0-9.]+)s (setup|call|teardown)\s+(\S+)")


def costs(text: str) -> dict:
    """``{node id without parameters: seconds}`` from pytest's ``--durations=0`` report."""
    out = defaultdict(float)
    for line in text.splitlines():
        m = LINE.match(line)
        if m:
            out[m.group(3).split("[")[0]] += float(m.group(1))
    return dict(out)


def read_list(path: Path) -> dict:
    """``{node id: seconds}`` of a ``slow.txt`` (the seconds recorded in its comments)."""
    out = {}
    for line in path.read_text().splitlines():
        node, _, note = line.partition("#")
        if node.strip():
            seconds = re.match(r"\s*([0-9.]+)", note)       # a note written by hand need not start with them
            out[node.strip()] = float(seconds.group(1)) if seconds else 0.0
    return out


def slow_tests(cost: dict, budget: float) -> list:
    """The most expensive tests, listed until the others cost at most ``budget`` seconds in all."""
    order = sorted(cost, key=lambda k: -cost[k])
    rest, slow = sum(cost.values()), []
    for node in order:
        if rest <= budget:
            break
        slow.append(node)
        rest -= cost[node]
    return slow


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("durations", help="the output of a full run with --durations=0")
    ap.add_argument("--budget", type=float, default=150.0, help="worker seconds of the quick tier (default 150)")
    ap.add_argument("--add", action="store_true", help="keep the list and add to it (durations of a quick-tier run)")
    a = ap.parse_args()
    cost = costs(Path(a.durations).read_text())
    listed = read_list(Path(__file__).parent / "slow.txt") if a.add else {}
    new = slow_tests({k: v for k, v in cost.items() if k not in listed}, a.budget)
    quick = sum(v for k, v in cost.items() if k not in listed and k not in new)
    kept = {line.partition("#")[0].strip(): line.partition("#")[2].strip()
            for line in (Path(__file__).parent / "slow.txt").read_text().splitlines()} if a.add else {}
    notes = {**{k: kept.get(k) or f"{v:.1f} s" for k, v in listed.items()},
             **{k: f"{cost[k]:.1f} s" + (" compiling" if a.add else "") for k in new}}
    slow, cost = sorted(notes), {**listed, **cost}
    lines = ["# Tests left out of the quick tier (python -m pytest -q -m \"not slow\"), by name, with their",
             "# measured worker seconds on a 2-core x86_64 machine (\"compiling\": in a run that had compiled",
             "# nothing yet); rewritten by python tests/tiers.py.",
             *(f"{n}  # {notes[n]}" for n in slow)]
    (Path(__file__).parent / "slow.txt").write_text("\n".join(lines) + "\n")
    print(f"{len(slow)} of {len(cost)} tests slow ({sum(cost[n] for n in slow):.0f} s); the quick tier {quick:.0f} s "
          f"of worker time")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
