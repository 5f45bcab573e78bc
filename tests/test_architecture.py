"""The house's rules, checked on the package's own imports (experiments/studies/architecture_figure.py draws them):
every module belongs to a floor, no import runs up a floor, no two modules import each other in a circle."""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "experiments" / "studies"))
from architecture_figure import FLOORS, ROOT as PKG, floor_of, imports  # noqa: E402


def _modules():
    return {".".join(p.relative_to(PKG.parent).with_suffix("").parts).removesuffix(".__init__")
            for p in PKG.rglob("*.py")}


def test_every_module_has_a_floor():
    stray = sorted(m for m in _modules() if m != "jaxsleigh" and floor_of(m) < 0)
    assert not stray, f"modules outside every floor of {[name for name, _ in FLOORS]}: {stray}"


def test_no_import_runs_up_a_floor():
    up = [(a, b) for a, b in imports() if floor_of(a) >= 0 and floor_of(b) > floor_of(a)]
    assert not up, up


def test_no_import_circle_between_modules():
    mods = _modules()

    def resolve(name):
        while name and name not in mods:
            name = name.rsplit(".", 1)[0] if "." in name else ""
        return name

    graph = {}
    for a, b in imports():
        a, b = a.removesuffix(".__init__"), resolve(b)
        if b and a != b and not a.startswith(b + "."):     # a package's face imported by its own modules
            graph.setdefault(a, set()).add(b)
    # Tarjan's strongly connected components
    index, low, stack, on, sccs, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                sccs.append(sorted(comp))

    for v in list(graph):
        if v not in index:
            visit(v)
    assert not sccs, f"import circles: {sccs}"


def test_only_the_integrate_floor_loops_over_time():
    """Time loops (``lax.scan``, ``while_loop``, ``fori_loop``, ``lax.map``) live in ``jaxsleigh/integrate/`` only:
    every other module integrates through it, so a change of the stepper reaches every front."""
    import ast

    loops = {"scan", "while_loop", "fori_loop", "map"}
    found = []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG)
        if rel.parts[0] == "integrate":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Attribute) and node.attr in loops and isinstance(node.value, ast.Attribute)
                    and node.value.attr == "lax"):
                found.append(f"{rel}:{node.lineno} lax.{node.attr}")
            elif isinstance(node, ast.ImportFrom) and (node.module or "").endswith("lax"):
                found += [f"{rel}:{node.lineno} from lax import {a.name}" for a in node.names if a.name in loops]
    assert not found, found


def test_each_command_line_module_only_parses_calls_and_prints():
    """A command's module holds its flags, one call into the library and its printing: at most 300 lines each (what a
    run does lives in the library, reachable from Python)."""
    long = {p.name: n for p in sorted((PKG / "cli").glob("*.py")) if (n := len(p.read_text().splitlines())) > 300}
    assert not long, long


def test_one_step_budget_rule():
    """Every default step budget comes from one rule, `jaxsleigh.integrate.horizon.attempt_budget` (a factor of the
    step and tolerance class times base steps, capped for int32): its factors and caps are read nowhere else, and its
    callers give the budgets of every front (a run, a float64 reference, a sampling period) as before."""
    import ast

    from jaxsleigh import StepSizeController
    from jaxsleigh.integrate.horizon import Horizon, default_max_steps, reference_max_steps
    from jaxsleigh.integrate.sampled import _period_budget

    names = {"BUDGET_FACTOR", "REFERENCE_FACTOR", "MAX_ATTEMPTS", "REFERENCE_MAX_ATTEMPTS"}
    found = []
    for path in sorted(PKG.rglob("*.py")):
        tree = ast.parse(path.read_text())
        rule = [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == "attempt_budget"]
        inside = {id(x) for f in rule for x in ast.walk(f)}
        found += [f"{path.relative_to(PKG)}:{n.lineno} {n.id}" for n in ast.walk(tree)
                  if isinstance(n, ast.Name) and n.id in names and isinstance(n.ctx, ast.Load) and id(n) not in inside]
    assert not found, found
    h = Horizon(100.0, 0.01, 10_000, 10_000)                       # 100 s at dt = 0.01, the final state saved
    assert (default_max_steps(h, True, "float32"), default_max_steps(h, True, "float64"),
            default_max_steps(h, False, "float32")) == (200_180, 300_270, 10_009)
    assert reference_max_steps(h) == 1_001_000 and reference_max_steps(Horizon(5e5, 0.01, 50_000_000, 1)) == 2 * 10**9
    assert default_max_steps(Horizon(5e5, 0.01, 50_000_000, 1), True, "float64") == 2**31 - 2
    assert [_period_budget(StepSizeController(method=m), 100, 10, d) for m, d in
            (("adaptive", "float32"), ("adaptive", "float64"), ("rk4", "float32"))] == [200, 300, 10]
