"""Every core (`jaxsleigh.cores`): one JAX CPU device per core from the first run (``import jaxsleigh`` changes no
JAX setting), chunks cut into parts that run concurrently, and results byte-identical whatever the number of cores."""
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh import cores
from jaxsleigh.plots.base import device_text


def _python(code: str, **env) -> str:
    full = dict(os.environ, JAX_PLATFORMS="cpu", JAXSLEIGH_NO_COMPILE_CACHE="1")
    for k in ("JAX_NUM_CPU_DEVICES", "JAXSLEIGH_CORES", "XLA_FLAGS"):
        full.pop(k, None)
    full.update(env)
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, env=full,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return r.stdout.strip().splitlines()[-1]


ONE = "[[1.0, 1.0, 0.5]], t_final=0.1, run=js.RunOptions(progress=False)"
FIRST_RUNS = {
    "run_ensemble": f"r = js.run_ensemble({ONE}); used = len(r.run_info['devices'])",
    "ensemble_of_a_law": "from jaxsleigh.controllers.registry import make_controller; "
                         f"r = js.run_ensemble({ONE}, controller=make_controller('astolfi')); "
                         "used = len(r.run_info['devices'])",
    "simulate": f"r = js.simulate({ONE}); used = len(r.run_info['devices'])",
    "solve": "js.solve(js.paper_gains(), [1.0, 1.0, 0.5], t_final=0.1).q_final.block_until_ready(); used = None",
}


@pytest.mark.parametrize("first", list(FIRST_RUNS))
def test_the_first_run_asks_for_one_device_per_core(first):
    """The import leaves JAX's device count alone; the first run, whichever it is, asks for one CPU device per core
    (JAX had not started; a law of one's own is evaluated once before the run), and its ``run_info`` names the
    devices it used: every one for an ensemble, one for a simulation (it runs on one device)."""
    out = json.loads(_python(f"""
        import json, jax, jaxsleigh as js
        from jaxsleigh.cores import available_cores
        at_import = jax.config.jax_num_cpu_devices
        {FIRST_RUNS[first]}
        print(json.dumps([at_import, len(jax.devices()), available_cores(), used]))
    """))
    at_import, devices, have, used = out
    assert at_import == -1 and devices == have >= 1
    assert used == {"run_ensemble": have, "ensemble_of_a_law": have, "simulate": 1, "solve": None}[first]


#: the starts of the test of three cores: 1200 random ones, 20 of them near theta = 0 (stiff stragglers)
STARTS = """
    rng = np.random.default_rng(4)
    ics = np.column_stack([rng.uniform(-3, 3, (1200, 2)), rng.uniform(0.3, 3, 1200) * rng.choice([-1, 1], 1200)])
    ics[:20, 2] = np.geomspace(2e-3, 0.1, 20)
"""

#: its float64 run (``cores`` to be given)
FLOAT64_RUN = ("js.run_ensemble(ics[:200], t_final=4.0, x64=True, "
               "run=js.RunOptions(chunk_size=200, cores={cores}, progress=False, audit=False))")


def test_the_first_runs_core_count_follows_the_settings():
    """``JAXSLEIGH_CORES=1`` gives one device, and a count the program chose itself (``jax_num_cpu_devices`` here;
    ``JAX_NUM_CPU_DEVICES`` in the test of three cores) is kept. With three devices the first run is the test of
    three cores' float64 run: JAX's persistent cache keys a program by the process's device count, so that the
    programs of the two processes of three devices are compiled once, whichever runs first."""
    code = """
        import jax, jaxsleigh as js
        r = js.run_ensemble([[1.0, 1.0, 0.5]], t_final=0.1, run=js.RunOptions(progress=False))
        print(len(jax.devices()), len(r.run_info["devices"]))
    """
    assert _python(code, JAXSLEIGH_CORES="1") == "1 1"
    three = (f"import jax, numpy as np, jaxsleigh as js; jax.config.update('jax_num_cpu_devices', 3)\n"
             f"{textwrap.dedent(STARTS)}\n"
             f"r = {FLOAT64_RUN.format(cores=None)}\n"
             "print(len(jax.devices()), len(r.run_info['devices']))")
    assert _python(three) == "3 3"


def test_results_are_byte_identical_on_one_and_three_cores():
    """Three forced CPU devices, so the test holds on a machine of any size: the adaptive engine (starts
    near theta = 0 included, so compaction and stragglers happen in some parts), float64 too, the plain
    fixed-step path, decimated trajectories and per-trajectory gains give the same bytes on 1 and 3 (an uneven
    split of every batch; 2 cores, the even split, added a third of the test's time and no case of its own)."""
    out = _python("""
        import hashlib, json, numpy as np, jaxsleigh as js
        STARTS
        def digest(r, *fields):
            h = hashlib.sha256()
            for f in fields:
                h.update(np.ascontiguousarray(getattr(r, f)).tobytes())
            return h.hexdigest()
        runs = {}
        for c in (1, 3):
            # (no accuracy audit: it changes no number of a result, and its float64 programs cost a third of the time)
            run = lambda chunk=None: js.RunOptions(chunk_size=chunk, cores=c, progress=False, audit=False)
            a = js.run_ensemble(ics, t_final=8.0, run=run(1200))
            b = FLOAT64_RUN
            p = js.run_ensemble(ics, t_final=8.0, stepsize=js.StepSizeController(method="rk4", check_passivity=False),
                                saveat=js.SaveAt(summaries=False), run=run(1200))
            # (300 starts, the 20 near theta = 0 among them: the saving loop runs every lane until the slowest
            # is done, 6,000 steps, and 900 lanes took twice as long as 300)
            s = js.run_ensemble(ics[:300], t_final=3.0, saveat=js.SaveAt(every=50), run=run(300))
            g = js.sweep(ics[:500], {"k": [0.5, 2.0]}, t_final=4.0, run=run())
            assert a.n_steps.max() > 4 * np.median(a.n_steps)        # stragglers: some parts are compacted
            runs[c] = [digest(a, "q_final", "p_final", "T_eps", "n_steps", "n_rejected", "u_energy", "status"),
                       digest(b, "q_final", "T_eps", "n_steps"), digest(p, "q_final", "p_final", "status"),
                       digest(s, "q", "p", "T_eps"), hashlib.sha256(np.ascontiguousarray(g.T_eps).tobytes()).hexdigest(),
                       a.run_info["devices"], str(b.q_final.dtype)]
        print(json.dumps(runs))
    """.replace("        STARTS\n", textwrap.indent(textwrap.dedent(STARTS).lstrip("\n"), " " * 8))
       .replace("FLOAT64_RUN", FLOAT64_RUN.format(cores="c")), JAX_NUM_CPU_DEVICES="3")
    runs = json.loads(out)
    assert runs["1"][:5] == runs["3"][:5]
    assert [len(runs[c][5]) for c in ("1", "3")] == [1, 3]
    assert runs["1"][6] == "float64"


def test_jax_started_first_is_said_once_with_the_way_out():
    if cores.available_cores() < 2:
        pytest.skip("one core: nothing to say")
    out = _python("""
        import warnings, jax, jax.numpy as jnp
        import jaxsleigh as js
        jnp.zeros(1).block_until_ready()          # JAX starts before jaxsleigh's first run
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            for _ in range(2):
                r = js.run_ensemble([[1.0, 1.0, 0.5]], t_final=1.0, run=js.RunOptions(progress=False))
        said = [str(x.message) for x in w if "cores" in str(x.message)]
        print(len(said), jax.config.jax_num_cpu_devices, len(r.run_info["devices"]), said[0] if said else "")
    """)
    assert out.startswith("1 -1 1 ") and "JAX_NUM_CPU_DEVICES=" in out and "Run jaxsleigh before" in out


def test_bad_core_counts_are_refused_or_named():
    with pytest.raises(ValueError, match="cores"):
        js.run_ensemble([[1.0, 1.0, 0.5]], t_final=1.0, run=js.RunOptions(cores=0, progress=False))
    with pytest.raises(ValueError, match="cores"):
        js.run_basin(np.array([[1.0, 1.0, 0.5]]), t_final=1.0, run=js.RunOptions(cores=1.5, progress=False))
    with pytest.raises(ValueError, match="devices is empty"):
        cores.workers([])
    out = _python("""
        import warnings
        import jax, jaxsleigh as js
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            js.run_ensemble([[1.0, 1.0, 0.5]], t_final=1.0, run=js.RunOptions(progress=False))
        print(len(jax.devices()) >= 1, any("JAXSLEIGH_CORES" in str(x.message) for x in w))
    """, JAXSLEIGH_CORES="many")
    assert out == "True True"


def test_run_parts_keeps_order_and_raises_the_first_error():
    import jax

    devs = jax.devices()[:1] * 3              # three threads on one device: order and errors, not speed
    assert cores.run_parts(lambda i: i * i, range(7), devs) == [0, 1, 4, 9, 16, 25, 36]

    def boom(i):
        if i == 3:
            raise RuntimeError("part 3 failed")
        return i

    with pytest.raises(RuntimeError, match="part 3 failed"):
        cores.run_parts(boom, range(6), devs)


def test_the_device_line_names_the_cores():
    assert device_text(None, {"devices": ["cpu:0", "cpu:1"]}) == "cpu, 2 cores"
    assert device_text(None, {"devices": ["cpu:0"]}) == "cpu:0"
    assert device_text(None, {"devices": ["cuda:0", "cuda:1"]}) == "2 devices: cuda:0, cuda:1"


def test_the_command_line_limits_the_cores_and_the_bytes_stay(tmp_path, capsys):
    """``--cores 1`` and ``--cores 2`` of two devices write the same basin, byte for byte, and say in their records
    how many devices ran; a bad count is refused with exit code 2 (argparse's, before any work: checked in this
    process, a third Python start-up would add nothing)."""
    from jaxsleigh.cli import main

    # 1200 starts: two parts of PART_SIZE, so that two cores run them; no accuracy audit (it writes nothing to the
    # .npz compared here, only to the run's record, and its float64 programs cost 40% of the first run)
    args = ["--x", "-2:2:40", "--y", "-1.5:1.5:30", "--theta", "0.9", "--t-final", "5", "--no-progress",
            "--audit-rows", "0"]
    for c in ("1", "2"):
        r = subprocess.run([sys.executable, "-m", "jaxsleigh.cli", "--no-compile-cache", "--cores", c, "basin", *args,
                            "--out", str(tmp_path / f"b{c}.npz")], capture_output=True, text=True, timeout=600,
                           env=dict(os.environ, JAX_NUM_CPU_DEVICES="2"))
        assert r.returncode == 0, r.stderr[-2000:]
    info = {c: json.loads((tmp_path / f"b{c}.run.json").read_text()) for c in ("1", "2")}
    assert [len(info[c]["devices"]) for c in ("1", "2")] == [1, 2]
    assert (tmp_path / "b1.npz").read_bytes() == (tmp_path / "b2.npz").read_bytes()
    capsys.readouterr()
    rc = main(["--cores", "none", "basin", *args, "--out", str(tmp_path / "x.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and "--cores" in err and "Traceback" not in err
    assert not (tmp_path / "x.npz").exists()


def test_bench_json_reports_cores_wall_ratio_and_steps():
    r = subprocess.run([sys.executable, "-m", "jaxsleigh.cli", "bench", "--json", "--n-ics", "64", "--t-final", "2"],
                       capture_output=True, text=True, timeout=600,
                       env=dict(os.environ, JAX_PLATFORMS="cpu", OMP_WAIT_POLICY="PASSIVE"))
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["cores"] == res["n_devices"] == cores.available_cores()
    assert res["accurate_mean_steps"] > 0 and res["wrong_or_nonfinite"] == 0
    assert len(res["load_average"]) == 3
    if res["c_limit_reason"] is None:          # a C compiler is here: the wall ratio against as many threads
        assert res["c_threads"] == res["cores"] and 0 < res["c_limit_ratio_wall"] < 10
        lo, hi = res["c_limit_ratio_wall_range"]
        assert lo <= res["c_limit_ratio_wall"] <= hi
    else:
        assert res["c_limit_ratio_wall"] is None and res["c_limit_reason"]


def test_interrupted_while_a_tail_runs_loses_nothing_and_resumes_to_the_same_bytes(tmp_path, monkeypatch):
    """Chunks of two parts: each part hands its stiff stragglers to the chunk's tail batch, which runs behind
    the next chunk's parts. Ctrl-C during the second chunk's parts still writes the first chunk; resuming
    ends with the uninterrupted run's numbers."""
    import jaxsleigh.studies.ensemble as ens

    rng = np.random.default_rng(11)
    ics = np.column_stack([rng.uniform(-3, 3, (5000, 2)), rng.uniform(0.3, 3, 5000) * rng.choice([-1, 1], 5000)])
    ics[::250, 2] = 0.01                                     # stragglers in every part
    run = js.RunOptions(chunk_size=2048, progress=False)
    whole = js.run_ensemble(ics, t_final=6.0, run=run)
    real, calls = ens.drive_final, []

    def interrupted(*a, **k):
        if k.get("stop_at"):
            calls.append(1)
            if len(calls) == 3:                              # the second chunk's first part
                raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(ens, "drive_final", interrupted)
    with pytest.raises(KeyboardInterrupt):
        js.run_ensemble(ics, t_final=6.0, run=run._replace(checkpoint_dir=tmp_path / "ck"))
    assert sorted(p.name for p in (tmp_path / "ck").glob("chunk_*.npz")) == ["chunk_000000.npz"]
    monkeypatch.setattr(ens, "drive_final", real)
    resumed = js.run_ensemble(ics, t_final=6.0, run=run._replace(checkpoint_dir=tmp_path / "ck", resume=True))
    assert resumed.run_info["chunks_reused"] == 1
    for f in ("q_final", "T_eps", "n_steps", "status", "u_energy"):
        np.testing.assert_array_equal(getattr(resumed, f), getattr(whole, f), err_msg=f)
    assert np.any(whole.n_steps > 20 * np.median(whole.n_steps))    # the stragglers were there


def test_the_three_fronts_take_one_cpu_chunk_size():
    """`run_ensemble`, `run_basin` and `sweep` resolve an unset chunk size to the same CPU default
    (`jaxsleigh.cores.CPU_CHUNK`), recorded in their settings; a chunk size given is kept."""
    ics = np.array([[1.0, -1.0, 0.5], [-2.0, 1.0, 2.0]])
    kw = dict(t_final=0.5, run=js.RunOptions(progress=False))
    got = {"run_ensemble": js.run_ensemble(ics, **kw).settings["chunk_size"],
           "run_basin": js.run_basin(ics, **kw).settings["chunk_size"],
           "sweep": js.sweep(ics, {"k": [0.1, 0.2]}, **kw).settings["chunk_size"]}
    assert got == dict.fromkeys(got, cores.CPU_CHUNK)
    assert js.run_ensemble(ics, t_final=0.5,
                           run=js.RunOptions(chunk_size=4, progress=False)).settings["chunk_size"] == 4
