"""labscript shot files drive shots: the ``llrs_`` globals become the shot's configuration, the results land in
the same file under ``/results/llrs``, and a file that already holds results is refused."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from engine.config import SystemConfig
from engine.records import CycleRecord, Outcome, ShotRecord
from engine.targets import build_target
from server.labscript import (
    RESULTS_GROUP,
    ShotFileError,
    read_shot_globals,
    read_shot_results,
    run_shot_file,
    shot_config,
    write_shot_results,
)


def make_shot_file(path: Path, globals_: dict[str, Any]) -> Path:
    """A file laid out like labscript's: evaluated globals on /globals, expressions in its subgroups."""
    with h5py.File(path, "w") as f:
        f.attrs["sequence_id"] = "20240101T120000_tweezers"
        f.attrs["run number"] = 7
        g = f.create_group("globals")
        for name, value in globals_.items():
            g.attrs[name] = value
        expressions = g.create_group("rearrangement")
        for name, value in globals_.items():
            expressions.attrs[name] = repr(value)
        f.create_group("devices/pulseblaster_0")
        f.create_dataset("script", data="from labscript import *\n")
    return path


LAB_GLOBALS = {
    "MOT_load_time": 0.25,  # not ours: ignored
    "llrs_algorithm": "exact-1d",
    "llrs_target": "centre",
    "llrs_target_count": np.int64(20),
    "llrs_max_cycles": 3,
    "llrs_loading_probability": 0.7,
}


class StandInEngine:
    """Runs 'shots' the way the server's engine would be called: ``run_shot(config or None)``."""

    def __init__(self, config: SystemConfig) -> None:
        self.config = config
        self.received: list[SystemConfig | None] = []

    def __call__(self, config: SystemConfig | None) -> ShotRecord:
        self.received.append(config)
        if config is not None:
            self.config = config
        cfg = self.config
        target = build_target(cfg.target, nx=cfg.array.nx, ny=cfg.array.ny)
        rng = np.random.default_rng(len(self.received))
        occ0 = rng.random(target.shape) < cfg.sim.loading_probability
        occ1 = occ0 | target
        cycles = [
            CycleRecord(index=0, occupancy=occ0, atoms=int(occ0.sum()), defects=int((target & ~occ0).sum()),
                        stage_s={"I.acquire": 0.024, "III.solve": 2e-5, "V.stream": 3e-4}, n_slots=12, n_steps=5,
                        latency_s=1.5e-4),
            CycleRecord(index=1, occupancy=occ1, atoms=int(occ1.sum()), defects=0, stage_s={"I.acquire": 0.023}),
        ]
        return ShotRecord(shot_id=41, config_digest=cfg.digest(), algorithm=cfg.solver.algorithm, target=target,
                          outcome=Outcome.SUCCESS, cycles=cycles, duration_s=0.06)


def test_a_labscript_shot_file_drives_a_shot_and_receives_its_results(tmp_path: Path) -> None:
    path = make_shot_file(tmp_path / "0007.h5", LAB_GLOBALS)
    engine = StandInEngine(SystemConfig())
    record = run_shot_file(path, engine, base_config=SystemConfig())
    assert record is not None
    (cfg,) = engine.received
    assert cfg is not None
    assert (cfg.solver.algorithm, cfg.target.kind, cfg.target.count) == ("exact-1d", "centre", 20)
    assert (cfg.loop.max_cycles, cfg.sim.loading_probability) == (3, 0.7)
    res = read_shot_results(path)
    assert res["outcome"] == "success" and res["success"] and res["shot_id"] == 41 and res["n_cycles"] == 2
    assert res["config_digest"] == cfg.digest() == SystemConfig.model_validate_json(res["config"]).digest()
    assert json.loads(res["globals"])["llrs_target_count"] == 20
    np.testing.assert_array_equal(res["occupancy"], np.stack([c.occupancy for c in record.cycles]))
    np.testing.assert_array_equal(res["target"], record.target)
    assert res["atoms"].tolist() == [c.atoms for c in record.cycles] and res["defects"].tolist()[-1] == 0
    assert res["stage_s"]["I.acquire"].tolist() == [0.024, 0.023]
    assert res["stage_s"]["III.solve"][0] == 2e-5 and np.isnan(res["stage_s"]["III.solve"][1])
    assert res["latency_s"][0] == 1.5e-4 and res["n_slots"].tolist() == [12, 0]
    # everything labscript put there is untouched, and nothing was written beside the file
    with h5py.File(path, "r") as f:
        assert f.attrs["run number"] == 7 and "devices/pulseblaster_0" in f
        assert f["globals"].attrs["MOT_load_time"] == 0.25
        assert list(f["results"]) == ["llrs"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0007.h5"]


def test_a_second_write_is_refused_and_changes_nothing(tmp_path: Path) -> None:
    path = make_shot_file(tmp_path / "0008.h5", LAB_GLOBALS)
    engine = StandInEngine(SystemConfig())
    run_shot_file(path, engine, base_config=SystemConfig())
    before = read_shot_results(path)
    with pytest.raises(
        ShotFileError, match=r"already holds LLRS results \(shot 41, outcome success.*never overwritten"
    ):
        run_shot_file(path, engine, base_config=SystemConfig())
    assert len(engine.received) == 1  # refused before running a shot
    with pytest.raises(ShotFileError, match="already holds LLRS results"):
        write_shot_results(path, engine(None))
    after = read_shot_results(path)
    assert after["written_at"] == before["written_at"]
    np.testing.assert_array_equal(after["occupancy"], before["occupancy"])


def test_a_file_without_llrs_globals_runs_on_the_current_configuration(tmp_path: Path) -> None:
    path = make_shot_file(tmp_path / "0009.h5", {"MOT_load_time": 0.25})
    engine = StandInEngine(SystemConfig())
    run_shot_file(path, engine, base_config=SystemConfig())
    assert engine.received == [None]
    assert read_shot_results(path)["outcome"] == "success"


@pytest.mark.parametrize(
    ("globals_", "match"),
    [
        ({"llrs_algoritm": "exact-1d"}, r"unknown llrs_ global\(s\) llrs_algoritm; recognised: llrs_algorithm"),
        ({"llrs_max_cycles": 0}, r"(?s)make an invalid configuration.*loop\.max_cycles \(global llrs_max_cycles = 0\)"),
        ({"llrs_config": "{not json"}, "llrs_config is not valid JSON"),
    ],
)
def test_bad_globals_fail_before_the_shot_naming_them(tmp_path: Path, globals_: dict[str, Any], match: str) -> None:
    path = make_shot_file(tmp_path / "bad.h5", globals_)
    engine = StandInEngine(SystemConfig())
    with pytest.raises(ShotFileError, match=match):
        run_shot_file(path, engine, base_config=SystemConfig())
    assert engine.received == []
    with h5py.File(path, "r") as f:
        assert RESULTS_GROUP not in f


def test_llrs_config_reaches_any_field_and_named_globals_win(tmp_path: Path) -> None:
    blob = json.dumps({"camera": {"em_gain": 150}, "solver": {"algorithm": "other"}})
    cfg = shot_config(SystemConfig(), {"llrs_config": blob, "llrs_algorithm": "exact-1d", "llrs_exposure_s": 0.03})
    assert cfg is not None
    assert (cfg.camera.em_gain, cfg.camera.exposure_s, cfg.solver.algorithm) == (150, 0.03, "exact-1d")


def test_a_failing_shot_is_recorded_as_a_fault_in_the_file(tmp_path: Path) -> None:
    path = make_shot_file(tmp_path / "0010.h5", LAB_GLOBALS)

    def broken(config: SystemConfig | None) -> ShotRecord:
        raise RuntimeError("camera: no frame within 0.6 s")

    with pytest.raises(RuntimeError):
        run_shot_file(path, broken, base_config=SystemConfig())
    res = read_shot_results(path)
    assert res["outcome"] == "fault" and "no frame within 0.6 s" in res["fault"] and not res["success"]


def test_a_disabled_shot_is_skipped_and_recorded(tmp_path: Path) -> None:
    path = make_shot_file(tmp_path / "0011.h5", {"llrs_enabled": False})
    engine = StandInEngine(SystemConfig())
    assert run_shot_file(path, engine, base_config=SystemConfig()) is None
    assert engine.received == [] and read_shot_results(path)["outcome"] == "skipped"


def test_missing_or_foreign_files_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(ShotFileError, match="no such shot file"):
        run_shot_file(tmp_path / "nope.h5", StandInEngine(SystemConfig()))
    assert not (tmp_path / "nope.h5").exists()
    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f.create_dataset("x", data=[1])
    with pytest.raises(ShotFileError, match="no /globals group"):
        read_shot_globals(tmp_path / "plain.h5")


@pytest.mark.slow
def test_a_shot_file_drives_the_real_engine_on_the_simulated_lab(tmp_path: Path) -> None:
    try:
        from drivers.factory import open_devices
        from engine.engine import Engine
    except Exception as err:  # noqa: BLE001 - the engine is finished elsewhere
        pytest.skip(f"engine does not import: {err}")
    from engine.config import load_config

    base = load_config(Path(__file__).resolve().parents[1] / "examples" / "chain-1x64.yaml")
    devices, lab = open_devices(base)
    engine = Engine(base, devices, lab=lab)

    def run_shot(config: SystemConfig | None) -> ShotRecord:
        if config is not None:
            engine.apply(config)
        return engine.run_shot()

    path = make_shot_file(tmp_path / "real.h5", {"llrs_target_count": 16, "llrs_max_cycles": 4})
    record = run_shot_file(path, run_shot, base_config=base)
    assert record is not None
    res = read_shot_results(path)
    assert res["outcome"] == record.outcome.value and res["n_cycles"] == len(record.cycles)
    assert int(res["target"].sum()) == 16
    devices.close()
