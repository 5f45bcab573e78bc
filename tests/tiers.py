"""Rewrite ``tests/slow.txt``, the tests left out of the quick tier, from measured durations.

    python -m pytest -q --durations=0 > durations.txt      # a full run
    python tests/tiers.py durations.txt [--budget 150]

Each test (its node id without parameters: all its cases together) costs the sum of its cases' setup and call
times. The most expensive tests are listed as slow until the rest, the quick tier, costs at most ``--budget``
seconds of worker time (two workers share it: about half of that in wall time, plus start-up). Tests marked
``@pytest.mark.slow`` in their file stay slow whatever this list says.
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
    a = ap.parse_args()
    cost = costs(Path(a.durations).read_text())
    slow = slow_tests(cost, a.budget)
    quick = sum(cost.values()) - sum(cost[n] for n in slow)
    lines = ["# Tests left out of the quick tier (python -m pytest -q -m \"not slow\"), by name, with their",
             "# measured worker seconds on a 2-core x86_64 machine; rewritten by python tests/tiers.py.",
             *(f"{n}  # {cost[n]:.1f} s" for n in sorted(slow))]
    (Path(__file__).parent / "slow.txt").write_text("\n".join(lines) + "\n")
    print(f"{len(slow)} of {len(cost)} tests slow ({sum(cost[n] for n in slow):.0f} s); the quick tier {quick:.0f} s "
          f"of worker time")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
