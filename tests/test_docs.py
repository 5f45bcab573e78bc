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
    """The page says as many notebooks as there are, that the import turns the compilation cache on and uses
    every core, and shows the call that moves the cache, which the API reference documents."""
    n = len(list((ROOT / "notebooks").glob("*.ipynb")))
    words = {4: "Four", 5: "Five", 6: "Six", 7: "Seven"}
    text = (DOCS / "getting-started.md").read_text()
    assert f"{words[n]} notebooks in `notebooks/`" in text
    assert "js.enable_compilation_cache(\"my_cache\")" in text and "JAXSLEIGH_CORES" in text
    assert "every core, and compiled programs kept per machine" in (ROOT / "README.md").read_text()
    assert 'id="jaxsleigh.enable_compilation_cache"' in (site / "api" / "index.html").read_text()


def test_readme_preset_numbers_are_the_committed_measurements():
    """The README's preset table quotes `experiments/preset_effort.py`'s JSON: for every preset and both start
    distributions, the median T_0.05 and the control energy's 25/50/75/90th percentiles as ratios to the paper's."""
    import json

    d = json.loads((DOCS / "figures" / "preset_effort.json").read_text())
    assert d["dtype"] == "float32" and d["command"] == "python experiments/preset_effort.py --atol 1e-8"
    assert d["atol"] == 1e-8
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert "`python experiments/preset_effort.py --atol 1e-8`" in readme
    for dist in ("readme", "wide"):
        rows = d["distributions"][dist]
        assert rows["n"] == 2048
        for name, f in rows["presets"].items():
            ratios = " / ".join(f"{f['energy_ratio_to_paper'][q]:.2f}" for q in ("p25", "p50", "p75", "p90"))
            if name == "paper":
                ratios = "1 / 1 / 1 / 1"
            assert f"{f['T_median']:.1f} s | {ratios}" in readme, (dist, name, f"{f['T_median']:.1f} s | {ratios}")
    sh, pa = (d["distributions"]["readme"]["presets"][k] for k in ("shaped", "paper"))
    assert f"{sh['mean_steps']:,.0f} mean steps (the paper's {pa['mean_steps']:,.0f})" in readme
    d64 = json.loads((DOCS / "figures" / "preset_effort_x64.json").read_text())
    assert d64["dtype"] == "float64" and d64["command"] == "python experiments/preset_effort.py --x64"
    bal64 = d64["distributions"]["readme"]["presets"]["balanced"]["energy_ratio_to_paper"]["p50"]
    assert f"float64 (`--x64`) agrees (median {bal64:.2f}x the paper's)" in readme
    for dist in ("readme", "wide"):                 # float64 at its defaults and float32 at atol 1e-8 agree
        for name, f in d64["distributions"][dist]["presets"].items():
            f32 = d["distributions"][dist]["presets"][name]
            for q, v in f["energy_ratio_to_paper"].items():
                assert abs(v - f32["energy_ratio_to_paper"][q]) < 0.01, (dist, name, q)
    bal = d["distributions"]["readme"]["presets"]["balanced"]
    tuning = (DOCS / "how-to" / "tuning.md").read_text()
    assert f"**{bal['energy_ratio_to_paper']['p75']:.2f}**" in tuning



def test_family_study_tables_quote_their_json():
    """The shaped-energy page's tables of the two tuner studies quote `experiments/shaped_study.py`'s JSON (shaped
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
    """The shaped-energy page's atol 1e-8 judgement (`experiments/shaped_held_out.py`) quotes the studies' JSON: the
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
    """The shaped-energy page's held-out table of Aicardi's law quotes `experiments/shaped_study.py --family aicardi`'s
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
    """The performance page and getting started quote `experiments/compile_cache.py`'s JSON: first and second fresh
    process of each README command, this tree against the baseline measured in the same run."""
    import json

    d = json.loads((DOCS / "figures" / "compile_cache.json").read_text())
    assert d["command"].startswith("python experiments/compile_cache.py --repeats 5 --baseline f036c14")
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


def test_issue20_limits_quote_their_json():
    """Where the performance and settled-phase pages say why issue 20's last targets are out of reach, they quote the
    scripts' JSON: the kernel table of `experiments/xla_kernel_structure.py` (kernels per step, rate, share of C), the
    per-lane costs of `experiments/block3_cost.py`, and every step count of `experiments/settled_phase_adopted.py`."""
    import json

    def rate(x):
        mantissa, exponent = f"{x:.2e}".split("e")
        return f"{mantissa}e{int(exponent)}"

    def of_c(x):
        return f"{x:.2f}" if x >= 0.1 else f"{x:.2g}"

    perf = (DOCS / "evidence" / "performance.md").read_text()
    k = json.loads((DOCS / "figures" / "xla_kernel_structure.json").read_text())
    assert k["cores"] == 1 and k["dtype"] == "float32" and k["command"].startswith("python experiments/xla_kernel_structure.py")
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
    assert s["command"] == "python experiments/settled_phase_adopted.py --also 72f4f8f"
    for gains, label in (("paper", "paper"), ("balanced", "previous balanced"), ("balanced_now", "present balanced"),
                         ("tuned", "tuned")):
        g = s["gains"][gains]
        steps = " → ".join(f"{g[c]['mean_steps']:,.0f}" for c in ("before", "also"))
        row = f"| {label} ({g['n']}) | {steps} → **{g['after']['mean_steps']:,.0f}** | **{g['steps_ratio']:.2f}x** / "
        assert row in settled, row
