"""The documentation site builds without a single warning and says what the code does.

``mkdocs build --strict`` fails on a broken link or anchor, a page missing from the navigation, an
object of the API reference that no longer exists, or a docstring mkdocstrings cannot render.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted(p for p in DOCS.rglob("*.md") if "notebooks" not in p.relative_to(DOCS).parts)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """Build the site once, into a temporary folder (nothing is written to the working tree)."""
    out = tmp_path_factory.mktemp("site")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    wall = time.perf_counter() - t0
    if proc.returncode != 0 and "No module named mkdocs" in proc.stderr:
        pytest.fail('mkdocs is not installed: pip install -e ".[test]" (or ".[docs]") installs it')
    warnings = [ln for ln in proc.stderr.splitlines() if ln.startswith(("WARNING", "ERROR"))]
    assert proc.returncode == 0, "mkdocs build --strict failed:\n" + "\n".join(warnings or proc.stderr.splitlines()[-30:])
    assert not warnings, warnings
    print(f"mkdocs build --strict: {wall:.1f} s")
    return out


def test_site_builds_with_api_reference(site):
    api = (site / "api" / "index.html").read_text()
    for name in ("studies.simulate.simulate", "run_ensemble", "run_basin", "Gains", "PlantParams", "Status", "vector_field",
                 "ClosedLoop", "EnsembleResult", "BasinResult", "Solution"):
        assert f'id="jaxsleigh.{name}"' in api, f"API reference lacks jaxsleigh.{name}"
    # the docstrings themselves are rendered, not only the headings
    assert "Simulate the closed loop" in api
    tuning = (site / "api" / "tuning" / "index.html").read_text()
    for name in ("tune", "TuneConfig", "LossConfig", "make_value_and_grad", "validate"):
        assert f'id="jaxsleigh.tuning.{name}"' in tuning, f"tuning API reference lacks {name}"


def _text(html: str) -> str:
    """The visible text of an HTML fragment (tags dropped, entities of quotes decoded)."""
    return re.sub(r"<[^>]+>", "", html).replace("&#39;", "'").replace("&quot;", '"').replace("&gt;", ">")


def test_api_reference_shows_the_function_once_with_its_signature(site):
    """``simulate`` is the function (not the module of the same name), ``Solution`` is listed once,
    the signature is formatted on its own lines with types and defaults, and no parameter that has a
    default is called "required"."""
    api = (site / "api" / "index.html").read_text()
    assert 'id="jaxsleigh.simulate"' not in api  # the module would list its members again
    assert api.count('id="jaxsleigh.Solution"') == 1 and 'id="jaxsleigh.studies.simulate.Solution"' not in api
    start = api.index('id="jaxsleigh.studies.simulate.simulate"')
    sig = _text(api[start:api.index("Simulate the closed loop", start)])
    # Ruff (a docs extra) formats long signatures one parameter a line
    assert "\n    t_final: float = 100.0,\n" in sig, sig
    assert "stepsize: Optional[StepSizeController] = None" in sig and "-> Solution" in sig
    for page in (site / "api").rglob("*.html"):
        body = _text(page.read_text().split('<div class="md-content"', 1)[-1])
        assert "required" not in body.lower(), f"{page.relative_to(site)} marks a parameter required"


def test_site_renders_maths_offline(site):
    """MathJax ships with the site (with its license) and no page loads a script or stylesheet from
    another host: offline, formulas still render."""
    vendored = site / "javascripts" / "mathjax" / "tex-svg.js"
    assert vendored.stat().st_size > 1_000_000 and b"MathJax" in vendored.read_bytes()
    assert "Apache License" in (DOCS / "javascripts" / "mathjax" / "LICENSE").read_text()
    pages = sorted(site.rglob("*.html"))
    assert len(pages) > 20
    for page in pages:
        html = page.read_text()
        external = re.findall(r'<script[^>]*\ssrc="((?:https?:)?//[^"]*)"', html)
        external += re.findall(r'<link[^>]*\shref="((?:https?:)?//[^"]*)"[^>]*rel="stylesheet"', html)
        external += re.findall(r'<link[^>]*rel="stylesheet"[^>]*\shref="((?:https?:)?//[^"]*)"', html)
        assert not external, f"{page.relative_to(site)} loads {external}"
        if page.name == "index.html" and "arithmatex" in html:
            assert "javascripts/mathjax/tex-svg.js" in html, f"{page.relative_to(site)} has maths but no MathJax"
    nb = (site / "notebooks" / "01_paper_reproduction" / "index.html").read_text()
    assert "javascripts/mathjax/tex-svg.js" in nb and "javascripts/mathjax-config.js" in nb


def test_notebook_pages_show_executed_outputs(site):
    """Each notebook has a page that shows every figure the committed (executed) notebook holds."""
    import nbformat

    notebooks = sorted((ROOT / "notebooks").glob("*.ipynb"))
    assert len(notebooks) >= 4
    for nb_path in notebooks:
        nb = nbformat.read(nb_path, as_version=4)
        n_images = sum("image/png" in out.get("data", {}) for cell in nb.cells if cell.cell_type == "code"
                       for out in cell.outputs)
        assert n_images >= 1, f"{nb_path.name} is committed without figure outputs"
        html = (site / "notebooks" / nb_path.stem / "index.html").read_text()
        shown = len(re.findall(r'<img[^>]*src="data:image/png;base64', html))
        assert shown == n_images, f"{nb_path.name}: the page shows {shown} of {n_images} figures"
        assert "Traceback" not in html, f"{nb_path.name}: the page shows an error"


def _status_table():
    text = (DOCS / "concepts.md").read_text()
    section = text.split("## Status codes", 1)[1].split("\n## ", 1)[0]
    return {int(code): name for code, name in re.findall(r"^\| (\d+) \| `([A-Z_]+)` \|", section, re.M)}


def test_status_table_names_every_code():
    from jaxsleigh import Status

    assert _status_table() == {int(s): s.name for s in Status}


def test_every_page_is_in_the_nav():
    nav = (ROOT / "mkdocs.yml").read_text()
    for page in PAGES:
        rel = page.relative_to(DOCS).as_posix()
        assert rel in nav, f"{rel} is not in mkdocs.yml's nav"


@pytest.mark.parametrize("path", [ROOT / "README.md", *PAGES], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_cites_nothing_outside_the_repository(path):
    text = path.read_text()
    for bad in ("MEASURED.md", "../shared", "shared/", "/work/"):
        assert bad not in text, f"{path.name} cites {bad!r}, which is not part of the repository"


def test_basin_pages_say_settled_within_the_horizon():
    text = (DOCS / "how-to" / "basins.md").read_text()
    assert "not basins of attraction" in text.lower() or "not a basin of attraction" in text.lower()
    assert "settled within the horizon" in text


def test_citation_and_license():
    yaml = pytest.importorskip("yaml")
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0" and cff["license"] == "MIT" and cff["type"] == "software"
    paper = cff["references"][0]
    assert paper["title"] == "Discontinuous energy shaping control of the Chaplygin sleigh"
    assert [a["family-names"] for a in paper["authors"]] == ["Ferguson", "Donaire", "Middleton"]
    lic = (ROOT / "LICENSE").read_text()
    assert lic.startswith("MIT License") and "Copyright (c) 2026 the jaxsleigh developers" in lic
    assert 'license = {text = "MIT"}' in (ROOT / "pyproject.toml").read_text()
    bib = (DOCS / "citing.md").read_text()
    assert "@inproceedings{" in bib and "Discontinuous energy shaping control of the {Chaplygin} sleigh" in bib


def test_getting_started_counts_the_notebooks_and_offers_the_cache(site):
    """The page says as many notebooks as there are, that the first run uses every core, and shows the call that
    turns the compilation cache on, which the README's example makes and the API reference documents."""
    n = len(list((ROOT / "notebooks").glob("*.ipynb")))
    words = {4: "Four", 5: "Five", 6: "Six", 7: "Seven"}
    text = (DOCS / "getting-started.md").read_text()
    assert f"{words[n]} notebooks in `notebooks/`" in text
    assert "js.enable_compilation_cache(\"my_cache\")" in text and "JAXSLEIGH_CORES" in text
    assert "js.enable_compilation_cache()        # compiled programs kept per machine" in (ROOT / "README.md").read_text()
    assert 'id="jaxsleigh.enable_compilation_cache"' in (site / "api" / "index.html").read_text()


def test_preset_numbers_are_the_committed_measurements():
    """The README's preset table and the full one of the tuning guide quote `experiments/studies/preset_effort.py`'s JSON.

    README: per preset, the median T_0.05 on the README's starts and the lowest and highest of the control energy's
    25/50/75/90th percentiles as ratios to the paper's. Tuning guide: for every preset and both start distributions,
    the median and all four ratios, the float64 check and the mean steps."""
    import json

    d = json.loads((DOCS / "figures" / "preset_effort.json").read_text())
    assert d["dtype"] == "float32" and d["command"] == "python experiments/studies/preset_effort.py"
    assert d["atol"] is None                                     # the default tolerances
    readme = " ".join((ROOT / "README.md").read_text().split())
    tuning = " ".join((DOCS / "how-to" / "tuning.md").read_text().split())
    for text in (readme, tuning):
        assert "`python experiments/studies/preset_effort.py`" in text
    quantiles = ("p25", "p50", "p75", "p90")
    for name, f in d["distributions"]["readme"]["presets"].items():
        r = [f["energy_ratio_to_paper"][q] for q in quantiles]
        energy = "1" if name == "paper" else f"{min(r):.2f}–{max(r):.2f}x"
        row = f"| `{name}` |"
        assert row in readme and f"| {f['T_median']:.1f} s | {energy} |" in readme, (name, energy)
    for dist in ("readme", "wide"):
        rows = d["distributions"][dist]
        assert rows["n"] == 2048
        for name, f in rows["presets"].items():
            ratios = " / ".join(f"{f['energy_ratio_to_paper'][q]:.2f}" for q in quantiles)
            if name == "paper":
                ratios = "1 / 1 / 1 / 1"
            assert f"{f['T_median']:.1f} s | {ratios}" in tuning, (dist, name, f"{f['T_median']:.1f} s | {ratios}")
    sh, pa = (d["distributions"]["readme"]["presets"][k] for k in ("shaped", "paper"))
    assert f"{sh['mean_steps']:,.0f} mean steps (the paper's {pa['mean_steps']:,.0f})" in tuning
    d64 = json.loads((DOCS / "figures" / "preset_effort_x64.json").read_text())
    assert d64["dtype"] == "float64" and d64["command"] == "python experiments/studies/preset_effort.py --x64"
    bal64 = d64["distributions"]["readme"]["presets"]["balanced"]["energy_ratio_to_paper"]["p50"]
    assert f"float64 (`--x64`) agrees (median {bal64:.2f}x the paper's)" in tuning
    for dist in ("readme", "wide"):                 # float64 and float32, each at its defaults, agree to 1%
        for name, f in d64["distributions"][dist]["presets"].items():
            f32 = d["distributions"][dist]["presets"][name]
            for q, v in f["energy_ratio_to_paper"].items():
                assert abs(f32["energy_ratio_to_paper"][q] / v - 1.0) < 0.01, (dist, name, q)
    bal = d["distributions"]["readme"]["presets"]["balanced"]
    assert f"**{bal['energy_ratio_to_paper']['p75']:.2f}**" in tuning


def test_the_tolerance_table_quotes_its_json_and_its_claims_hold():
    """The accuracy page's table of tolerances quotes `experiments/studies/tolerance_cost.py`'s JSON row by row, and
    what the page says of it holds there: T_eps is early for every settled start at every tolerance (the 99th
    percentile is negative), its median grows with the tolerance, float64 at 1e-6 errs as float32 does (truncation,
    not rounding), no start settles in one run only, and the default has no start (basin) or one (wide) beyond 1 ms."""
    import json

    d = json.loads((DOCS / "figures" / "tolerance_cost.json").read_text())
    assert d["command"] == "python experiments/studies/tolerance_cost.py" and d["n"] == 1024
    page = (DOCS / "evidence" / "accuracy.md").read_text()
    assert "`python experiments/studies/tolerance_cost.py`" in page
    b, w = d["dists"]["basin"]["runs"], d["dists"]["wide"]["runs"]
    ms = lambda x: f"{1e3 * x:.2f}".replace("-", "\u2212")  # noqa: E731
    for key, rb in b.items():
        rw = w[key]
        tb, tw = rb["T_eps_diff_s"], rw["T_eps_diff_s"]
        cells = (f"| {rb['mean_steps']:,.0f} / {rw['mean_steps']:,.0f} | {ms(tb['median'])} / {ms(tw['median'])} | "
                 f"{ms(tb['p1'])} / {ms(tw['p1'])} | {ms(max(tb['p99'], tw['p99']))} |")
        assert cells in page, (key, cells)
        assert tb["p99"] < 0 and tw["p99"] < 0 and rb["settled_in_one_only"] == rw["settled_in_one_only"] == 0
    medians = [b[f"float32 {tol}"]["T_eps_diff_s"]["median"] for tol in ("1e-06", "2e-06", "3e-06", "1e-05")]
    assert medians == sorted(medians, reverse=True)
    f32, f64 = b["float32 1e-06"]["T_eps_diff_s"], b["float64 1e-06"]["T_eps_diff_s"]
    assert abs(f32["median"] / f64["median"] - 1) < 0.1
    assert b["float32 1e-06"]["T_eps_diff_s"]["over_1e-3"] == 0 and w["float32 1e-06"]["T_eps_diff_s"]["over_1e-3"] <= 1
    saved = 1 - b["float32 1e-05"]["mean_steps"] / b["float32 1e-06"]["mean_steps"]
    assert f"saves {100 * saved:.0f}% of the steps of a basin" in " ".join(page.split())


def test_family_study_tables_quote_their_json():
    """The shaped-energy page's tables of the two tuner studies quote `experiments/studies/shaped_study.py`'s JSON (shaped
    and paper families): each tuner's best training objective, and every held-out median T and energy ratio row."""
    import json

    page = " ".join((DOCS / "evidence" / "shaped-energy.md").read_text().split())
    for fam, label in (("shaped", "shaped family, gradient's best (`shaped`)"), ("paper", "paper family, gradient's best")):
        d = json.loads((DOCS / "figures" / f"{fam}_study.json").read_text())
        assert d["dtype"] == "float32" and d["n_train"] == 1024
        for tuner in ("gradient", "cma"):
            assert f"{d[tuner]['best_value']:.4f}" in page, (fam, tuner)
        for dist, name in (("readme", "README"), ("wide", "wide")):
            f = d["held_out"][dist]["gradient"]
            ratios = " / ".join(f"{f['energy_ratio_to_paper'][q]:.2f}" for q in ("p25", "p50", "p75", "p90"))
            assert f"| {label} | {name} | {f['T_median']:.1f} | {ratios} |" in page, (fam, dist)


def test_family_studies_judged_at_atol_1e_8_quote_their_json():
    """The shaped-energy page's atol 1e-8 judgement (`experiments/studies/shaped_held_out.py`) quotes the studies' JSON: the
    shaped family's held-out table (both tuners, both tolerances) and the paper family's gradient ratios."""
    import json

    page = " ".join((DOCS / "evidence" / "shaped-energy.md").read_text().split())

    def ratios(f):
        return " / ".join(f"{f['energy_ratio_to_paper'][q]:.2f}" for q in ("p25", "p50", "p75", "p90"))

    d = json.loads((DOCS / "figures" / "shaped_study.json").read_text())
    assert d["held_out_atol"]["atol"] == 1e-8
    for key, label in (("gradient", "gradient's best (`shaped`)"), ("cma", "CMA-ES's best")):
        for dist, name in (("readme", "README"), ("wide", "wide")):
            f, f0 = d["held_out_atol"][dist][key], d["held_out"][dist][key]
            tight = ratios(f) if key == "gradient" else f"**{ratios(f)}**"
            assert f"| {label} | {name} |" in page and f"| {tight} | {ratios(f0)} |" in page, (key, dist)
            assert f0["T_median"] == pytest.approx(f["T_median"], abs=0.05)      # the tolerance moves energy, not time
    p = json.loads((DOCS / "figures" / "paper_study.json").read_text())["held_out_atol"]
    assert f"{ratios(p['readme']['gradient'])} on the README's starts and {ratios(p['wide']['gradient'])}" in page


def test_aicardi_study_table_quotes_its_json():
    """The shaped-energy page's held-out table of Aicardi's law quotes `experiments/studies/shaped_study.py --family aicardi`'s
    JSON: CMA-ES's best training objective and each held-out row's median T and energy ratios."""
    import json

    page = " ".join((DOCS / "evidence" / "shaped-energy.md").read_text().split())
    d = json.loads((DOCS / "figures" / "aicardi_study.json").read_text())
    assert d["dtype"] == "float32" and d["n_train"] == 1024 and d["family"] == "aicardi"
    assert f"{d['cma']['best_value']:.4f}" in page
    labels = {"start": "Aicardi, defaults", "gradient": "Aicardi, gradient's best", "cma": "Aicardi, CMA-ES's best"}
    for dist, name in (("readme", "README"), ("wide", "wide")):
        for key, label in labels.items():
            if key not in d["held_out"][dist]:
                continue
            f = d["held_out"][dist][key]
            ratios = " / ".join(f"{f['energy_ratio_to_paper'][q]:.2f}" for q in ("p25", "p50", "p75", "p90"))
            assert f"| {label} | {name} | {f['T_median']:.1f} | {ratios} |" in page, (key, dist)


def test_start_up_figures_are_the_committed_measurement():
    """The performance page and getting started quote `experiments/performance/compile_cache.py`'s JSON: first and second fresh
    process of each README command, this tree against the baseline measured in the same run."""
    import json

    d = json.loads((DOCS / "figures" / "compile_cache.json").read_text())
    assert d["command"].startswith("python experiments/performance/compile_cache.py --repeats 5 --baseline f036c14")
    perf = (DOCS / "evidence" / "performance.md").read_text()
    start = " ".join((DOCS / "getting-started.md").read_text().split())
    m = d["medians"]
    for name in ("simulate", "basin", "x64", "paper"):
        new, old = m[f"{name} | this tree"], m[f"{name} | f036c14"]
        assert f"{old['first_s']:.2f} / {old['second_s']:.2f} s ({old['ratio']:.1f}x" in perf, name
        assert f"{new['first_s']:.2f} / {new['second_s']:.2f} s" in perf and f"{new['ratio']:.1f}x" in perf, name
    new, old = m["simulate | this tree"], m["simulate | f036c14"]
    assert (f"takes {new['first_s']:.2f} s in a fresh process with an empty cache folder and {new['second_s']:.2f} s "
            f"in the next one ({new['ratio']:.1f}x)") in start
    assert f"{old['first_s']:.2f} s and {old['second_s']:.2f} s ({old['ratio']:.1f}x)" in start
    assert new["ratio"] >= 3.0


def test_kernel_and_step_limits_quote_their_json():
    """Where the performance and settled-phase pages say why the kernel and the step go no faster, they quote the
    scripts' JSON: the kernel table of `experiments/performance/xla_kernel_structure.py` (kernels per step, rate, share of C), the
    per-lane costs of `experiments/performance/block3_cost.py`, and every step count of `experiments/studies/settled_phase_adopted.py`."""
    import json

    def rate(x):
        mantissa, exponent = f"{x:.2e}".split("e")
        return f"{mantissa}e{int(exponent)}"

    def of_c(x):
        return f"{x:.2f}" if x >= 0.1 else f"{x:.2g}"

    perf = (DOCS / "evidence" / "performance.md").read_text()
    k = json.loads((DOCS / "figures" / "xla_kernel_structure.json").read_text())
    assert k["cores"] == 1 and k["dtype"] == "float32" and k["command"].startswith("python experiments/performance/xla_kernel_structure.py")
    r = k["rows"]
    pairs = (("the library's (cache blocks of 256) / the same rebuilt by the script", ("library", "rebuilt")),
             ("blocks of 128 / 512", ("block_128", "block_512")),
             ("one division less per evaluation (k / w1² as (k · 1/w1) · 1/w1)", ("shared_reciprocal",)),
             ("stage points inside the field, slopes materialised (`optimization_barrier`)", ("stage_in_field",)),
             ("stage points written row by row, nothing materialised (XLA fuses the whole step)", ("inline_step",)),
             ("the state as five rows (a tuple carry)", ("rows_carry",)),
             ("`drive_plain` / `run_ensemble` around the library's kernel", ("drive_plain", "run_ensemble")),
             ("C reference, one thread", ("c",)))
    for label, names in pairs:
        kernels = " / ".join(str(r[n]["kernels_per_step"]) for n in names if "kernels_per_step" in r[n])
        row = (f"| {label} |{f' {kernels} ' if kernels else ' '}| "
               + " / ".join(rate(r[n]["traj_steps_per_cpu_s"]) for n in names) + " | "
               + " / ".join(of_c(r[n]["of_c"]) for n in names) + " |")
        assert row in perf, row
    assert r["library"]["max_rel_diff_vs_library"] == 0.0 and r["rebuilt"]["max_rel_diff_vs_library"] == 0.0

    settled = " ".join((DOCS / "evidence" / "settled-phase.md").read_text().split())
    b = json.loads((DOCS / "figures" / "block3_cost.json").read_text())["rows"]
    assert (f"e^M of a 3x3 matrix at {b['expm_3x3']['us_per_lane']:.2f} µs per lane" in settled
            and f"at {b['expm_12x12']['us_per_lane']:.1f} µs, against **{b['library_step']['us_per_lane']:.2f} µs" in settled)
    s = json.loads((DOCS / "figures" / "settled_phase_adopted.json").read_text())
    assert s["command"] == "python experiments/studies/settled_phase_adopted.py --also 72f4f8f"
    for gains, label in (("paper", "paper"), ("balanced", "previous balanced"), ("balanced_now", "present balanced"),
                         ("tuned", "tuned")):
        g = s["gains"][gains]
        steps = " → ".join(f"{g[c]['mean_steps']:,.0f}" for c in ("before", "also"))
        row = f"| {label} ({g['n']}) | {steps} → **{g['after']['mean_steps']:,.0f}** | **{g['steps_ratio']:.2f}x** / "
        assert row in settled, row


# --- The pages speak to users: what was measured and why, not how the work was organised -----------------------

# Files a user reads: the README, the changelog, every page, the notebooks (their cells and printed outputs), the
# experiment scripts the pages cite, and the site's configuration. (CITATION.cff is left out: its "issue" is the
# paper's journal issue.)
_USER_FILES = sorted({ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "mkdocs.yml",
                      *DOCS.rglob("*.md"), *(ROOT / "notebooks").glob("*.ipynb"),
                      *(p for ext in ("py", "sh", "c") for p in (ROOT / "experiments").rglob(f"*.{ext}"))})

# Patterns of the project's own process (case-insensitive, except the acronym). A "session" inside an identifier (a
# test named `test_python_session_...`) does not match; SLURM's tasks ("one task per GPU") do not match either.
_PROCESS_WORDS = [
    ("an issue number", r"\bissues?\s*#?\s*\d", re.I),
    ("an issue in a name", r"issue\d|issue_|#issue", re.I),
    ("an issue", r"\bissues?\b", re.I),
    ("a session", r"\bsessions?\b", re.I),
    ("a task in the work's sense", r"\b(?:this|the) task\b|\btasks? \d", re.I),
    ("the people or the plan", r"\bengineers?\b|\bthe brief\b|\bwork items?\b|\bdevice time\b|\blent\b|\btickets?\b",
     re.I),
    ("the CEO", r"\bCEO\b", 0),
]


def _user_text(path: Path) -> str:
    """The words a reader sees: a notebook's cells and its printed outputs (not its images), a file's text."""
    if path.suffix == ".ipynb":
        import json

        nb = json.loads(path.read_text())
        parts = []
        for cell in nb["cells"]:
            parts.append("".join(cell["source"]))
            for out in cell.get("outputs", []):
                parts.append("".join(out.get("text", "")))
                parts.append("".join(out.get("data", {}).get("text/plain", "")))
        return "\n".join(parts)
    return re.sub(r"https?://\S+", "", path.read_text())       # a link's address is not prose


def test_file_names_speak_of_what_they_hold():
    for folder in (DOCS, ROOT / "experiments", ROOT / "notebooks"):
        for path in folder.rglob("*"):
            assert "issue" not in path.name.lower(), f"{path.relative_to(ROOT)}: name it after what it holds"


@pytest.mark.parametrize("path", _USER_FILES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_pages_speak_of_the_software_not_of_its_making(path):
    """README, docs, notebooks and experiments say what was measured and why it matters; a reader has no issue
    tracker, session or plan to look up."""
    text = _user_text(path)
    found = []
    for what, pattern, flags in _PROCESS_WORDS:
        for m in re.finditer(pattern, text, flags):
            line = text.count("\n", 0, m.start()) + 1
            found.append(f"line {line}: {what}: {text[max(0, m.start() - 40):m.end() + 40]!r}")
    assert not found, f"{path.relative_to(ROOT)} speaks of the project's process:\n" + "\n".join(found)


def test_process_patterns_catch_what_they_should():
    """The patterns above on sentences of the kind they exist for, and on ones they must leave alone."""
    def hits(text):
        return [what for what, pattern, flags in _PROCESS_WORDS if re.search(pattern, text, flags)]

    # the samples with numbers are put together, so that this file names no issue number itself
    for bad in ("Issue" + " 9's 2x target is not met", "## Adopted (issue" + " 20)", "measured in this session",
                "a session's device time", "experiments/issue" + "20_details.py", "the issue's 4.1e8", "see #issue",
                "the CEO asked", "other engineers' jobs", "on a lent machine"):
        assert hits(bad), bad
    for good in ("`test_python_session_fills_the_same_folder_as_the_command_line`", "one task per GPU",
                 "#SBATCH --ntasks-per-node=4", "--stop-fraction 0.001", "tissue", "ceo_of_mass"):
        assert not hits(good), (good, hits(good))


def _version_of_pyproject():
    project = (ROOT / "pyproject.toml").read_text().split("[project]", 1)[1].split("\n[", 1)[0]
    return re.search(r'^version = "([^"]+)"$', project, re.M).group(1)


def test_one_version_in_pyproject_citation_changelog_and_bibtex():
    """pyproject's version is the citation's, the BibTeX entry's and the changelog's newest entry; the changelog
    lists its versions newest first, and the README and the site link it."""
    version = _version_of_pyproject()
    cff = re.search(r"^version: *([^\s]+)$", (ROOT / "CITATION.cff").read_text(), re.M).group(1)
    assert cff == version, (cff, version)
    assert f"version = {{{version}}}," in (DOCS / "citing.md").read_text()
    changelog = (ROOT / "CHANGELOG.md").read_text()
    versions = re.findall(r"^## \[(\d+)\.(\d+)\.(\d+)\]", changelog, re.M)
    assert versions and ".".join(versions[0]) == version, (versions[:1], version)
    as_numbers = [tuple(map(int, v)) for v in versions]
    assert as_numbers == sorted(as_numbers, reverse=True), "the changelog lists its versions newest first"
    assert "](CHANGELOG.md)" in (ROOT / "README.md").read_text()


@pytest.mark.slow
def test_concepts_page_global_trap_and_fields_hold():
    """What the concepts page says of a law's numbers holds: the page's two blocks, run as written (on a shorter
    horizon): a law that reads a global keeps the value of its first run; a law whose number is a field gives a
    new run for a new value."""
    import numpy as np

    text = (DOCS / "concepts.md").read_text()
    section = text.split("**A law's numbers are its fields, never Python globals.**", 1)[1].split("\n**", 1)[0]
    blocks = [b.replace("t_final=20.0", "t_final=2.0") for b in re.findall(r"```python\n(.*?)```", section, re.S)]
    assert len(blocks) == 2
    head = ("from typing import NamedTuple\nimport jax.numpy as jnp\nimport numpy as np\nimport jaxsleigh as js\n"
            "ics = np.array([[-3.0, -2.0, np.pi / 8], [1.0, 1.0, 0.0]])\n")
    trap, fields = {}, {}
    exec(compile(head + blocks[0], "concepts.md", "exec"), trap)
    assert np.array_equal(trap["a"].q_final, trap["b"].q_final)          # K = 5.0 changed nothing
    exec(compile(head + blocks[1], "concepts.md", "exec"), fields)
    assert not np.allclose(fields["a"].q_final, fields["b"].q_final)     # k = 5.0 is a new run
    assert np.allclose(fields["a"].q_final, trap["a"].q_final)           # the same law at k = 1


@pytest.mark.slow
def test_the_trajectory_loss_example_prints_what_the_tuning_page_says(capsys):
    """The how-to's loss along the path runs as written and prints the losses and derivatives the page quotes."""
    page = (DOCS / "how-to" / "tuning.md").read_text()
    section = page.split("## A loss along the trajectory", 1)[1]
    code = section.split("```python", 1)[1].split("```", 1)[0]
    exec(compile(code, "tuning.md", "exec"), {})
    printed = [[float(x) for x in re.findall(r"Array\((-?[\d.e+-]+)", line)]
               for line in capsys.readouterr().out.splitlines() if line.strip()]
    quoted = re.search(r"a loss of (\S+) with d/dk = (\S+) for the\s+continuous law, and (\S+) with d/dk = (\S+) "
                       r"behind", section)
    want = [float(x.rstrip(",")) for x in quoted.groups()]
    assert len(printed) == 2 and all(len(p) == 2 for p in printed), printed
    for got, w in zip(printed[0] + printed[1], want):
        assert got == pytest.approx(w, rel=2e-3), (printed, want)
