import numpy as np
import pytest

from engine.config import TargetConfig
from engine.targets import build_target, centre_target


def test_centre_chain_is_contiguous_and_centred() -> None:
    t = centre_target(nx=64, ny=1, count=32)
    assert t.sum() == 32
    assert np.flatnonzero(t[0]).tolist() == list(range(16, 48))


def test_centre_grid_is_full_width_band() -> None:
    t = centre_target(nx=32, ny=64, count=1024)
    assert t.sum() == 1024
    assert t[16:48].all() and not t[:16].any() and not t[48:].any()


def test_rectangle_and_mask() -> None:
    t = build_target(TargetConfig(kind="rectangle", row0=1, col0=2, rows=2, cols=3), nx=8, ny=4)
    assert t.sum() == 6 and t[1:3, 2:5].all()
    m = build_target(TargetConfig(kind="mask", mask=["101", "010"]), nx=3, ny=2)
    assert m.tolist() == [[True, False, True], [False, True, False]]


@pytest.mark.parametrize(
    ("cfg", "match"),
    [
        (TargetConfig(kind="centre", count=30), "multiple of nx"),
        (TargetConfig(kind="rectangle", rows=9, cols=1), "does not fit"),
        (TargetConfig(kind="mask", mask=["10"]), "rows"),
        (TargetConfig(kind="mask", mask=["1x1", "000"]), "'0'/'1'"),
        (TargetConfig(kind="mask", mask=["000", "000"]), "no trap"),
    ],
)
def test_bad_targets(cfg: TargetConfig, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        build_target(cfg, nx=3 if cfg.kind == "mask" else 8, ny=2 if cfg.kind == "mask" else 4)
