"""The static tones of an AOD axis, read from the configuration in one place, and the one Nyquist check.

Every user of the comb (the configuration's own checks, the waveform bank, the simulated lab's decoder)
reads it through ``tones_of`` and checks the sample rate with ``check_below_nyquist``, so a CSV file means
the same thing everywhere and a comb too high for the card is refused with the same words.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import NamedTuple, Protocol

import numpy as np

from engine.errors import ConfigError

__all__ = ["ToneAxis", "Tones", "check_below_nyquist", "schroeder_phases", "tones_of"]


class Tones(NamedTuple):
    """The static tone of every site of one axis (float64 arrays, one entry per site)."""

    frequency_hz: np.ndarray
    amplitude: np.ndarray  # fraction of full scale
    phase_rad: np.ndarray


class ToneAxis(Protocol):
    """How one axis's tones are configured (``engine.config.ToneAxisConfig`` is one): an evenly spaced comb
    ``start_hz + k * spacing_hz``, or a CSV file with columns ``alpha,nu,phi`` that overrides it."""

    @property
    def start_hz(self) -> float: ...
    @property
    def spacing_hz(self) -> float: ...
    @property
    def amplitude(self) -> float: ...
    @property
    def phases(self) -> str: ...
    @property
    def csv(self) -> str | None: ...


def schroeder_phases(n: int) -> np.ndarray:
    """Low-crest-factor phases for ``n`` equal tones: ``phi_k = -pi k (k - 1) / n`` (mod 2 pi)."""
    k = np.arange(n, dtype=np.float64)
    return np.mod(-np.pi * k * (k - 1) / n, 2 * np.pi)


def tones_of(tones: ToneAxis, n: int, axis: str) -> Tones:
    """The static tones of the ``n`` sites of ``axis`` ('x' or 'y') as configured: the comb (at the
    configured amplitude, Schroeder or zero phases; ``continuous`` phases depend on the slot and are set by
    ``engine.waveforms.axis_tones``, zeros here) or the first ``n`` rows of the CSV (header names may
    carry spaces). Raises ``ConfigError`` naming the file and line when the CSV cannot be used; what the
    tones must satisfy against the sample rate and slot is checked by their users."""
    if tones.csv is None:
        freq = tones.start_hz + tones.spacing_hz * np.arange(n, dtype=np.float64)
        phase = schroeder_phases(n) if tones.phases == "schroeder" else np.zeros(n)
        return Tones(freq, np.full(n, tones.amplitude, dtype=np.float64), phase)
    path, where = tones.csv, f"array.{axis}_tones.csv"
    try:
        with Path(path).open(newline="") as fh:
            reader = csv.DictReader(fh)
            cols = [c.strip() for c in (reader.fieldnames or [])]
            missing = [c for c in ("alpha", "nu", "phi") if c not in cols]
            if missing:
                raise ConfigError(
                    f"{where} {path}: needs columns alpha,nu,phi (amplitude fraction, Hz, rad); "
                    f"missing {','.join(missing)} in its first line"
                )  # the file's text is never quoted: the path could name any file, secrets included
            reader.fieldnames = cols
            rows = []
            for line, rec in enumerate(reader, start=2):
                try:
                    rows.append((float(rec["alpha"]), float(rec["nu"]), float(rec["phi"])))
                except (TypeError, ValueError):
                    raise ConfigError(f"{where} {path} line {line}: alpha, nu and phi must be numbers") from None
    except OSError as err:
        raise ConfigError(f"{where}: cannot read tone file {path}: {err.strerror or err}") from None
    if len(rows) < n:
        raise ConfigError(f"{where} {path} has {len(rows)} tone rows but the {axis} axis has {n} sites")
    arr = np.asarray(rows[:n], dtype=np.float64)
    return Tones(arr[:, 1].copy(), arr[:, 0].copy(), arr[:, 2].copy())


def check_below_nyquist(
    low_hz: float, high_hz: float, sample_rate_hz: float, *, where: str, fix: str = "",
    error: type[ValueError] = ConfigError,
) -> None:
    """Raise ``error`` unless every tone between ``low_hz`` and ``high_hz`` lies in (0, Nyquist): a card
    sampling at ``sample_rate_hz`` cannot play (and a decoder cannot tell apart) a tone at or above half of it."""
    nyquist_hz = sample_rate_hz / 2
    if low_hz <= 0 or high_hz >= nyquist_hz:
        raise error(
            f"{where}: tones span {low_hz:g}..{high_hz:g} Hz, outside (0, Nyquist = {nyquist_hz:g} Hz)"
            + (f"; {fix}" if fix else "")
        )
