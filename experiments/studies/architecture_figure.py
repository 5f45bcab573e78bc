"""Draw the layers of the package (docs/figures/architecture.png) from the package itself: one band per
floor, the modules of each sub-package, and how many names each floor imports from the floors below.

    python experiments/studies/architecture_figure.py [--out docs/figures/architecture.png]

It also checks the rule the figure states: no module imports one of a floor above its own (exit 1 if
one does, naming it).
"""
from __future__ import annotations

import argparse
import ast
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2] / "jaxsleigh"
#: floors from the ground up; a floor may import only floors below it (and itself)
FLOORS = [
    ("base", ["errors", "validate", "progress", "status", "cache", "cores", "jax_private"]),
    ("files", ["files"]),
    ("model", ["model", "controllers"]),
    ("integrate", ["integrate"]),
    ("studies", ["studies"]),
    ("tuning / plots", ["tuning", "plots"]),
    ("cli", ["cli"]),
]


def floor_of(module: str) -> int:
    """Floor index of a dotted module name under jaxsleigh (``None`` for the package face)."""
    parts = module.split(".")
    head = parts[1] if len(parts) > 1 else ""
    for i, (_, members) in enumerate(FLOORS):
        if head in members:
            return i
    return -1


def imports() -> list[tuple[str, str]]:
    """(importer, imported) module pairs inside the package, from the source (top-level and local imports)."""
    pairs = []
    for path in ROOT.rglob("*.py"):
        mod = ".".join(path.relative_to(ROOT.parent).with_suffix("").parts)
        pkg = mod.rsplit(".", 1)[0] if path.name != "__init__.py" else mod.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("jaxsleigh")):
                if node.level:
                    base = pkg.split(".")[: len(pkg.split(".")) - (node.level - 1)]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module
                # ``from .. import tuning`` imports the sub-package ``tuning``: the names are the targets
                pairs.extend((mod, f"{target}.{a.name}") for a in node.names)
            elif isinstance(node, ast.Import):
                pairs.extend((mod, a.name) for a in node.names if a.name.startswith("jaxsleigh"))
    return pairs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/figures/architecture.png")
    args = ap.parse_args()
    pairs = [(a, b) for a, b in imports() if floor_of(a) >= 0 and floor_of(b) >= 0]
    upward = [(a, b) for a, b in pairs if floor_of(b) > floor_of(a)]
    for a, b in upward:
        print(f"upward import: {a} -> {b}", file=sys.stderr)
    counts = Counter((floor_of(a), floor_of(b)) for a, b in pairs if floor_of(a) != floor_of(b))

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import textwrap

    fig, ax = plt.subplots(figsize=(12, 8))
    ax.set_axis_off()
    n = len(FLOORS)
    for i, (name, members) in enumerate(FLOORS):
        y = i
        mods = []
        for m in members:
            p = ROOT / m
            if p.is_dir():
                mods.append(f"{m}/  " + ", ".join(sorted(q.stem for q in p.glob("*.py") if q.stem != "__init__")))
            elif (ROOT / f"{m}.py").exists():
                mods.append(f"{m}.py")
        if name == "base":
            mods = ["  ".join(mods)]
        lines = [ln for m in mods for ln in textwrap.wrap(m, 100, subsequent_indent="    ")]
        below = ", ".join(f"{FLOORS[d][0]} {c}" for (sf, d), c in sorted(counts.items()) if sf == i and d < i)
        ax.add_patch(plt.Rectangle((0, y + 0.06), 10, 0.86, facecolor="#e8eef8", edgecolor="#4a5d8a"))
        ax.text(0.15, y + 0.82, name, fontsize=12, fontweight="bold", va="top")
        ax.text(0.15, y + 0.56, "\n".join(lines), fontsize=7.5, va="top", family="monospace")
        ax.text(10.15, y + 0.5, ("names imported: " + below) if below else "imports nothing of the package",
                fontsize=7.5, va="center", color="#333")
    ax.set_xlim(0, 13)
    ax.set_ylim(0, n)
    ax.set_title("jaxsleigh's layers: each floor imports only the floors below it"
                 f" ({len(pairs)} names imported inside the package, {len(upward)} upward)", fontsize=11)
    fig.text(0.01, 0.01, "python experiments/studies/architecture_figure.py (drawn from the package's own imports)",
             fontsize=7, color="0.4")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110, bbox_inches="tight")
    print(f"wrote {args.out}: {len(pairs)} imports, {len(upward)} upward")
    return 1 if upward else 0


if __name__ == "__main__":
    sys.exit(main())
