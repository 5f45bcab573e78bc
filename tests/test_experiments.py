"""The experiments: they use only jaxsleigh's public API, each is in experiments/README.md, and every path that names
one (in the pages, the package, the tests, the scripts themselves) names a file that exists."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXPERIMENTS = ROOT / "experiments"
SCRIPTS = sorted(p for p in EXPERIMENTS.rglob("*") if p.is_file() and p.suffix in (".py", ".sh", ".c")
                 and "__pycache__" not in p.parts)

#: the documented methods and fields of named tuples: public, with an underscore only to keep them apart from fields
NAMEDTUPLE_API = {"_replace", "_asdict", "_fields", "_make", "_field_defaults"}


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__") and name not in NAMEDTUPLE_API


def _root(node: ast.AST):
    """The name an attribute chain ``a.b.c`` starts from (``a``), or None."""
    while isinstance(node, ast.Attribute):
        node = node.value
    return node.id if isinstance(node, ast.Name) else None


def _is_jaxsleigh(module: str) -> bool:
    return module == "jaxsleigh" or module.startswith("jaxsleigh.")


def private_uses(source: str, where: str = "<source>") -> list[str]:
    """Where ``source`` reaches a private name of jaxsleigh: imports a private module or name from it, or reads or
    writes ``x._name`` (or ``getattr(x, "_name")``) on a name bound to jaxsleigh or one of its objects. Programs
    the script runs in a fresh process (a string that parses as Python and imports jaxsleigh) are checked too."""
    tree = ast.parse(source)
    bound, found = set(), []

    def say(node, what):
        found.append(f"{where}:{node.lineno}: {what}")

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if _is_jaxsleigh(a.name):
                    bound.add(a.asname or a.name.split(".")[0])
                    if any(_private(part) for part in a.name.split(".")):
                        say(node, f"import {a.name}")
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and _is_jaxsleigh(node.module):
            if any(_private(part) for part in node.module.split(".")):
                say(node, f"from {node.module} import ...")
            for a in node.names:
                bound.add(a.asname or a.name)
                if _private(a.name):
                    say(node, f"from {node.module} import {a.name}")
        elif (isinstance(node, ast.Assign) and isinstance(node.value, ast.Call) and node.value.args
              and isinstance(node.value.args[0], ast.Constant) and isinstance(node.value.args[0].value, str)
              and _is_jaxsleigh(node.value.args[0].value)):            # m = importlib.import_module("jaxsleigh.x")
            bound.update(t.id for t in node.targets if isinstance(t, ast.Name))
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr) and _root(node) in bound:
            say(node, ast.unparse(node))
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "setattr")
              and len(node.args) >= 2 and _root(node.args[0]) in bound and isinstance(node.args[1], ast.Constant)
              and isinstance(node.args[1].value, str) and _private(node.args[1].value)):
            say(node, ast.unparse(node))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and "import" in node.value \
                and "jaxsleigh" in node.value:
            try:
                found += private_uses(node.value, f"{where}:{node.lineno} (program run in a fresh process)")
            except SyntaxError:                                          # prose, not a program
                pass
    return found


def test_the_check_finds_private_names_and_passes_public_ones():
    """The check above on code of the kinds it exists for, and on code it must leave alone."""
    bad = ["from jaxsleigh.studies.bench import _w_chart_starts",
           "from jaxsleigh.integrate._kernels import run",
           "import jaxsleigh.integrate.engine as engine\nkey = engine._args_key(args)",
           "import jaxsleigh.studies.ensemble as ens\nens._Chunks._run_tail = f",
           "from jaxsleigh.integrate import engine\nf = getattr(engine, '_plain_specialised')",
           "import jaxsleigh as js\njs.studies.ensemble._run_chunks(x)",
           "import importlib\nens = importlib.import_module('jaxsleigh.studies.ensemble')\nens._Chunks",
           "CODE = '''\nfrom jaxsleigh.studies import bench as B\nB._w_chart_starts(1, 2, 3)\n'''"]
    good = ["import jaxsleigh as js\njs.run_basin(js.sample_starts(8))",
            "from jaxsleigh.integrate import engine\nengine.PLAIN_CPU_OPTIONS",
            "from jaxsleigh import ShapedGains\nShapedGains._fields",
            "from jaxsleigh.tuning import SearchConfig\nc = SearchConfig()\nc._replace(n=1)",
            "import argparse\nargparse._SubParsersAction",
            "from cmaes import CMA\nopt = CMA(mean=[0], sigma=1)\nopt._rng",
            "TEXT = 'we import jaxsleigh and avoid its _private names.'"]
    for src in bad:
        assert private_uses(src), src
    for src in good:
        assert not private_uses(src), (src, private_uses(src))


@pytest.mark.parametrize("path", [p for p in SCRIPTS if p.suffix == ".py"],
                         ids=lambda p: p.relative_to(ROOT).as_posix())
def test_experiments_use_only_the_public_api(path):
    found = private_uses(path.read_text(), path.relative_to(ROOT).as_posix())
    assert not found, "private names of jaxsleigh (use public calls):\n" + "\n".join(found)


def test_every_experiment_is_in_the_index():
    index = (EXPERIMENTS / "README.md").read_text()
    missing = [p.relative_to(EXPERIMENTS).as_posix() for p in SCRIPTS
               if p.relative_to(EXPERIMENTS).as_posix() not in index]
    assert not missing, f"experiments/README.md lists no line for {missing}"


def test_every_script_is_in_a_folder_of_its_kind():
    loose = [p.name for p in SCRIPTS if p.parent == EXPERIMENTS and p.name != "common.py"]
    assert not loose, f"put {loose} in experiments/studies/ or experiments/performance/"


_PATH = re.compile(r"experiments/[\w./-]*[\w/]")


def _files_that_name_experiments():
    for folder, pattern in ((ROOT, "README.md"), (ROOT, "CHANGELOG.md"), (ROOT / "docs", "**/*.md"),
                            (ROOT / "docs" / "figures", "**/*.json"), (ROOT / "notebooks", "*.ipynb"),
                            (ROOT / "jaxsleigh", "**/*.py"), (ROOT / "jaxsleigh", "**/*.json"),
                            (ROOT / "jaxsleigh", "**/*.c"), (ROOT / "experiments", "**/*.*"),
                            (ROOT / "tests", "**/*.py")):
        for p in folder.glob(pattern):
            if p.is_file() and p.name != "test_docs.py" and "__pycache__" not in p.parts:   # test_docs: bad examples
                yield p


def test_every_path_to_an_experiment_exists():
    """A script moved or renamed leaves no page, docstring, test or recorded command pointing at its old path."""
    stale = []
    for p in _files_that_name_experiments():
        for m in _PATH.finditer(p.read_text(errors="replace")):
            target = m.group(0).rstrip(".")
            if not (ROOT / target).exists():
                stale.append(f"{p.relative_to(ROOT)}: {target}")
    assert not stale, "paths to experiments that do not exist:\n" + "\n".join(sorted(set(stale)))
