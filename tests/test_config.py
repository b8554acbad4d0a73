"""Configuration: examples load, bad values fail naming the field, YAML round-trips."""

from pathlib import Path

import pytest

from engine.config import ConfigError, SystemConfig, config_from_dict, load_config, save_config

EXAMPLES = sorted(Path(__file__).resolve().parents[1].joinpath("examples").glob("*.yaml"))


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_examples_are_valid(path: Path) -> None:
    config = load_config(path)
    assert config.name == path.stem


def test_yaml_round_trip(tmp_path: Path) -> None:
    config = load_config(EXAMPLES[0])
    save_config(config, tmp_path / "copy.yaml")
    again = load_config(tmp_path / "copy.yaml")
    assert again == config
    assert again.digest() == config.digest()


@pytest.mark.parametrize(
    ("data", "field", "hint"),
    [
        ({"array": {"nx": 0}}, "array.nx", "greater than or equal to 1"),
        ({"array": {"ny": 4, "trap_source": "aod"}}, "array", "ny = 1"),
        ({"array": {"x_tones": {"spacing_hz": 1.05e6}}}, "array.x_tones.spacing_hz", "multiple of"),
        ({"array": {"x_tones": {"start_hz": 300e6}}}, "array.x_tones", "outside (0, Nyquist = 3.12e+08 Hz)"),
        ({"waveforms": {"shape": "square"}}, "waveforms.shape", "min-jerk"),
        ({"sim": {"loading_probability": 1.5}}, "sim.loading_probability", "less than or equal to 1"),
        ({"target": {"count": 100}}, "target.count", "between 1 and nx"),
        ({"imaging": {"psf_box_px": 6}}, "imaging", "odd"),
        ({"camera": {"roi_width_px": 100}}, "camera", "outside the 100x16 ROI"),
        ({"bogus": 1}, "bogus", "Extra inputs"),
    ],
)
def test_bad_values_name_the_field(data: dict, field: str, hint: str) -> None:
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, source="test")
    message = str(info.value)
    assert field and field in message  # every error names the field it is about
    assert hint in message


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("array: [unclosed")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
    scalar = tmp_path / "scalar.yaml"
    scalar.write_text("42")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(scalar)


def test_defaults_are_valid() -> None:
    config = SystemConfig()
    assert config.waveforms.slot_samples == 6240


@pytest.mark.parametrize("imaging", [{"read_noise_e": 5e-324}, {"electrons_per_count": 5e-324}])
def test_denormal_camera_physics_is_refused(imaging: dict) -> None:
    """A schemathesis find: a denormal read noise or ADC gain overflowed the simulated camera's noise model."""
    with pytest.raises(ConfigError, match=f"sim.imaging.{next(iter(imaging))}"):
        config_from_dict({"sim": {"imaging": imaging}})
    assert config_from_dict({"sim": {"imaging": {"read_noise_e": 0.0}}}).sim.imaging.read_noise_e == 0.0
