"""One record of the plant in every file that records one: a result's settings (`test_cli_plotting`), a tuner's
gains file and an optimum's settings all hold `plant_to_dict`'s record (the damping by its class, with its parameters), and a gains
file of an earlier version, which named the damping by its short name, still loads."""
from __future__ import annotations

import json

import numpy as np

import jaxsleigh as js
from jaxsleigh.studies.config import plant_to_dict


def test_a_result_a_gains_file_and_an_optimum_record_the_plant_alike(tmp_path):
    from jaxsleigh.tuning import TuneConfig
    from jaxsleigh.tuning.runs import HeldOut, tune_run

    plant = js.plant_params(2.0, 1.0, 0.5, "viscous")
    want = plant_to_dict(plant)
    assert want["damping"] == "ViscousDamping" and set(want["damping_params"]) == {"c1", "c2"}
    tune_run(tmp_path / "g.json", config=TuneConfig(steps=1, batch=2), plant=plant, held_out=HeldOut(n=0))
    assert json.loads((tmp_path / "g.json").read_text())["meta"]["plant"] == want
    res = js.optimum(np.array([[1.0, 1.0, 0.5]]), horizons=(5.0,), plant=plant,
                     options=js.OptimumOptions(intervals=4, outer=1, inner=2, guesses=1))
    assert res.settings["plant"] == want


def test_a_gains_file_with_the_earlier_plant_record_still_loads(tmp_path):
    from jaxsleigh.model.params import gains_to_dict, load_gains, paper_gains, save_gains

    path = tmp_path / "g.json"
    save_gains(paper_gains(), path, how="by hand")
    doc = json.loads(path.read_text())
    doc["meta"]["plant"] = {"m": 2.0, "J": 1.0, "l": 1.0, "damping": "coulomb"}        # the tuners' record before
    path.write_text(json.dumps(doc))
    assert gains_to_dict(load_gains(path)) == gains_to_dict(paper_gains())
