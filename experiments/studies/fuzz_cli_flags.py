r"""Every option of every command that takes a value, given awkward values: is the answer always a message?

    python experiments/studies/fuzz_cli_flags.py [--tokens nan,inf,...] [--out out/fuzz_cli_flags.json]

Runs ``jaxsleigh.cli.main`` in this process for each command (with the few options it needs), once per option and
value (default values: nan, inf, -inf, 1e999, -1, 0, abc, 1e-320, 3000000000 and the empty string), with the
functions where the commands' work begins replaced by a stub (as in
``tests/test_fuzz_inputs.py::test_no_numeric_flag_of_any_command_shows_a_traceback``, which runs two of the values).
A run that reaches the stub passed every check; exit code 2 with ``jaxsleigh: error: ...`` is a refusal; anything
else (an exception escaping, exit code 1, a traceback on stderr, or a run still going after 20 s) is reported as bad.
Prints the counts and every bad run; writes them to ``--out``.
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import importlib
import io
import json
import os
import signal
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
TOKENS = ["nan", "inf", "-inf", "1e999", "-1", "0", "abc", "1e-320", "3000000000", ""]


class _Stop(BaseException):
    pass


def _stub(*a, **k):
    raise _Stop("work")


def _alarm(*a):
    raise _Stop("alarm")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tokens", default=",".join(TOKENS), help="comma-separated values to give every option")
    ap.add_argument("--out", default="out/fuzz_cli_flags.json")
    args = ap.parse_args(argv)
    os.environ.setdefault("JAXSLEIGH_NO_COMPILE_CACHE", "1")
    from jaxsleigh import cli
    from test_fuzz_inputs import COMMAND_ARGS, OUTPUTS, PATH_OPTIONS, WORK   # the test's commands and stubs

    for mod, name in WORK:
        setattr(importlib.import_module(mod), name, _stub)
    signal.signal(signal.SIGALRM, _alarm)
    tmp = tempfile.mkdtemp()
    base, outputs, paths = COMMAND_ARGS, OUTPUTS, PATH_OPTIONS
    commands = next(a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    kinds, bad = collections.Counter(), []
    for command, parser in commands.items():
        out = ["--out", f"{tmp}/{outputs[command]}"] if command in outputs else []
        flags = [a.option_strings[-1] for a in parser._actions if a.option_strings and a.nargs != 0
                 and not isinstance(a, argparse.BooleanOptionalAction) and a.option_strings[-1] not in paths]
        for flag in flags:
            for token in args.tokens.split(","):
                argv_ = [command, *base.get(command, []), *out, flag, token]
                err = io.StringIO()
                signal.alarm(20)
                try:
                    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                        rc = cli.main(argv_)
                    kind = "refused" if rc == 2 and err.getvalue().startswith("jaxsleigh: error: ") else f"exit {rc}"
                except _Stop as e:
                    kind = "work reached" if str(e) == "work" else "still running after 20 s"
                except BaseException as e:                       # noqa: BLE001 - what we look for
                    kind = f"{type(e).__name__}: {str(e)[:200]}"
                finally:
                    signal.alarm(0)
                ok = kind in ("refused", "work reached", "exit 0") and "Traceback" not in err.getvalue()
                kinds["ok: " + kind if ok else "bad"] += 1
                if not ok:
                    bad.append({"argv": argv_[1 + len(base.get(command, [])) + len(out):], "command": command,
                                "answer": kind, "stderr_tail": err.getvalue()[-300:]})
    doc = {"command": "python experiments/studies/fuzz_cli_flags.py " + " ".join(argv or sys.argv[1:]),
           "runs": sum(kinds.values()), "counts": dict(kinds), "bad": bad}
    print(json.dumps({k: doc[k] for k in ("runs", "counts")}))
    for b in bad:
        print(json.dumps(b))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(doc, indent=1))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
