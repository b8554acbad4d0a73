"""How the speed of a move costs atoms: survival per transfer and per one-site step from the slot's duration and
transition shape, the site spacing and the trap.

Physics (classical atom, Gaussian tweezer ``-U exp(-2 r^2 / w^2)``, thermal energy ``E ~ Gamma(3, kT)`` as for a
3D harmonic trap; an atom is lost when its energy exceeds the barrier that holds it):

- **Step** (the tweezer carries the atom ``d`` along the shape ``x(t) = d s(t / T)``). In the tweezer's frame the
  atom feels the inertial force ``m a(t)``, which tilts the trap and lowers its barrier: with
  ``alpha = m a w / U`` the barrier falls from ``U`` to ``U_eff(alpha)`` and vanishes at
  ``alpha = 2 exp(-1/2) = 1.21`` (the most a Gaussian trap can hold: ``a_hold = 1.21 U / (m w)``). Spill
  survival is ``P(E < U_eff(alpha_peak))`` at the shape's peak acceleration (``5.77 d / T^2`` for min-jerk).
  After the move the atom keeps the oscillation the move excited, energy
  ``dE = (m / 2) |int a(t) exp(i omega t) dt|^2`` (a driven harmonic oscillator, radial trap frequency
  ``omega = sqrt(4 U / (m w^2))``; the Fourier-transform result of Couvert et al., EPL 83, 13001 (2008)),
  and survives if ``E + dE < U``. The step survives both: ``P(E < min(U_eff, U - dE))``.
- **Transfer** (slm extract / implant: the tweezer's depth ramps with the shape over a static trap). The
  trap frequency changes from ``omega_i`` to ``omega_f`` (``omega^2`` proportional to the depth); a ramp of
  finite duration leaves the energy multiplied by ``(omega_f / omega_i) Q`` with Husimi's non-adiabaticity
  factor ``Q >= 1`` (``Q = 1`` adiabatic; ``(omega_i^2 + omega_f^2) / (2 omega_i omega_f)`` sudden), computed
  by integrating the oscillator through the ramp. Extraction deepens the trap (static ``U_s`` to
  ``U_s + U_t``), implantation makes it shallower again, and the atom is lost if its energy then exceeds
  ``U_s``. The pair's survival is split evenly between its two transfers (``p_transfer = sqrt(p_pair)``),
  since the world charges every transfer alike.

Everything else a real move loses atoms to (scattering, intensity noise, imperfect overlap at the hand-over)
is the speed-independent survival the configuration gives (``sim.survival_transfer`` / ``survival_step``);
the world multiplies the two. What the model leaves out: anharmonic shifts of the trap frequency,
heating that accumulates over many moves (each move starts from the thermal state), the static traps' pull
on a tweezer passing between them, and tunnelling.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq
from scipy.special import gammainc

from engine.config import MoveLossConfig
from engine.waveforms import shape_curve

__all__ = [
    "TrapParameters",
    "barrier_fraction",
    "move_survival",
    "step_survival",
    "trap_parameters",
    "transfer_survival",
]

BOLTZMANN_J_PER_K = 1.380649e-23
ATOMIC_MASS_KG = 1.66053906660e-27
#: Tilt (``m a w / U``) at which a Gaussian trap's barrier vanishes: the peak of ``4 x exp(-2 x^2)``.
ALPHA_HOLD = 2.0 * math.exp(-0.5)
#: Samples per slot when evaluating a shape's acceleration and the excitation integral.
_SHAPE_SAMPLES = 4001
#: Above this many radians of trap oscillation per ramp, a depth ramp is adiabatic (for min-jerk, Q - 1 is
#: 1.4e-6 at 12 rad and falls steeply beyond).
_ADIABATIC_RADIANS = 60.0


@dataclass(frozen=True)
class TrapParameters:
    """The atom and the traps, in laboratory units (defaults: see ``engine.config.MoveLossConfig``)."""

    tweezer_depth_mk: float
    static_depth_mk: float
    waist_um: float
    temperature_uk: float
    atom_mass_amu: float

    def __post_init__(self) -> None:
        for name in ("tweezer_depth_mk", "static_depth_mk", "waist_um", "temperature_uk", "atom_mass_amu"):
            if not getattr(self, name) > 0:
                raise ValueError(f"TrapParameters.{name} must be positive (got {getattr(self, name)})")

    @property
    def mass_kg(self) -> float:
        return self.atom_mass_amu * ATOMIC_MASS_KG

    @property
    def kt_j(self) -> float:
        return BOLTZMANN_J_PER_K * self.temperature_uk * 1e-6

    def depth_j(self, depth_mk: float) -> float:
        return BOLTZMANN_J_PER_K * depth_mk * 1e-3

    def radial_omega(self, depth_mk: float) -> float:
        """Radial trap frequency (rad/s) of a Gaussian trap of this depth: ``sqrt(4 U / (m w^2))``."""
        w = self.waist_um * 1e-6
        return math.sqrt(4.0 * self.depth_j(depth_mk) / (self.mass_kg * w * w))


def trap_parameters(moves: MoveLossConfig) -> TrapParameters:
    """The trap parameters of a ``sim.moves`` configuration."""
    return TrapParameters(
        tweezer_depth_mk=moves.tweezer_depth_mk,
        static_depth_mk=moves.static_depth_mk,
        waist_um=moves.waist_um,
        temperature_uk=moves.temperature_uk,
        atom_mass_amu=moves.atom_mass_amu,
    )


def barrier_fraction(alpha: float) -> float:
    """Barrier of the tilted Gaussian ``-exp(-2 x^2) + alpha x`` (x in waists), as a fraction of the depth."""
    if alpha <= 0.0:
        return 1.0
    if alpha >= ALPHA_HOLD:
        return 0.0

    def force(x: float) -> float:
        """Zero at the well and at the barrier."""
        return -4.0 * x * math.exp(-2.0 * x * x) - alpha

    def potential(x: float) -> float:
        return -math.exp(-2.0 * x * x) + alpha * x

    well = brentq(force, -0.5, 0.0)
    top = brentq(force, -0.5 - 20.0, -0.5)
    return max(0.0, potential(top) - potential(well))


def _thermal_below(energy_j: float, kt_j: float) -> float:
    """P(E < energy) for a thermal atom in a 3D harmonic trap (E ~ Gamma(3, kT))."""
    return float(gammainc(3.0, energy_j / kt_j)) if energy_j > 0 else 0.0


def _acceleration_profile(shape: str, sharpness: float) -> tuple[np.ndarray, np.ndarray]:
    """(u, s''(u)) on [0, 1]: the shape's acceleration in units of distance / duration^2."""
    u = np.linspace(0.0, 1.0, _SHAPE_SAMPLES)
    s = shape_curve(shape, sharpness, u)
    return u, np.gradient(np.gradient(s, u), u)


def step_survival(
    slot_duration_s: float, shape: str, sharpness: float, site_spacing_um: float, trap: TrapParameters
) -> float:
    """Survival of one one-site step from its speed alone (spill at the peak acceleration, then the residual
    oscillation against the full depth)."""
    duration = float(slot_duration_s)
    distance = site_spacing_um * 1e-6
    u, s2 = _acceleration_profile(shape, sharpness)
    accel = distance / duration**2 * s2  # m/s^2 along the slot
    m = trap.mass_kg
    depth = trap.depth_j(trap.tweezer_depth_mk)
    alpha = m * float(np.abs(accel).max()) * trap.waist_um * 1e-6 / depth
    omega = trap.radial_omega(trap.tweezer_depth_mk)
    t = u * duration
    kick = np.trapezoid(accel * np.exp(1j * omega * t), t)  # velocity amplitude of the residual oscillation
    residual_j = 0.5 * m * abs(kick) ** 2
    return _thermal_below(min(barrier_fraction(alpha) * depth, depth - residual_j), trap.kt_j)


def _husimi_q(omega_sq: np.ndarray, duration_s: float) -> float:
    """Husimi's Q for ``x'' = -omega(t)^2 x`` with ``omega^2`` sampled evenly over the ramp (RK4)."""
    omega_i, omega_f = math.sqrt(omega_sq[0]), math.sqrt(omega_sq[-1])
    n = omega_sq.size - 1
    h = duration_s / n
    # two fundamental solutions at once: c (c(0) = 1, c'(0) = 0) and s (s(0) = 0, s'(0) = 1)
    x = np.array([1.0, 0.0])
    v = np.array([0.0, 1.0])
    for i in range(n):
        w0, w2 = omega_sq[i], omega_sq[i + 1]
        w1 = 0.5 * (w0 + w2)
        k1x, k1v = v, -w0 * x
        k2x, k2v = v + 0.5 * h * k1v, -w1 * (x + 0.5 * h * k1x)
        k3x, k3v = v + 0.5 * h * k2v, -w1 * (x + 0.5 * h * k2x)
        k4x, k4v = v + h * k3v, -w2 * (x + h * k3x)
        x = x + h / 6.0 * (k1x + 2 * k2x + 2 * k3x + k4x)
        v = v + h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
    (c, s), (dc, ds) = x, v
    # an oscillation of any phase, energy E_i, ends with <E_f> = E_i (omega_f / omega_i) Q
    return ((dc * dc + omega_f**2 * c * c) + omega_i**2 * (ds * ds + omega_f**2 * s * s)) / (2.0 * omega_i * omega_f)


def _ramp_q(
    from_mk: float, to_mk: float, duration_s: float, shape: str, sharpness: float, trap: TrapParameters
) -> float:
    """Q of a depth ramp ``from -> to`` along the shape over the slot (1 when adiabatic)."""
    omega_min = trap.radial_omega(min(from_mk, to_mk))
    if omega_min * duration_s > _ADIABATIC_RADIANS:
        return 1.0
    n = max(400, int(100 * trap.radial_omega(max(from_mk, to_mk)) * duration_s / (2 * math.pi)))
    depth = from_mk + (to_mk - from_mk) * shape_curve(shape, sharpness, np.linspace(0.0, 1.0, n + 1))
    omega_sq = np.array([trap.radial_omega(d) ** 2 for d in depth])
    return max(1.0, _husimi_q(omega_sq, duration_s))  # Q >= 1; the integrator's round-off can dip below


def transfer_survival(slot_duration_s: float, shape: str, sharpness: float, trap: TrapParameters) -> float:
    """Survival of one transfer (the square root of an extract + implant pair's) from the ramps' speed."""
    static, both = trap.static_depth_mk, trap.static_depth_mk + trap.tweezer_depth_mk
    kt = trap.kt_j
    # extraction: static -> static + tweezer; the energy scales by (omega_f / omega_i) Q
    scale_up = math.sqrt(both / static) * _ramp_q(static, both, slot_duration_s, shape, sharpness, trap)
    p_extract = _thermal_below(trap.depth_j(both), kt * scale_up)
    scale_down = math.sqrt(static / both) * _ramp_q(both, static, slot_duration_s, shape, sharpness, trap)
    p_implant = _thermal_below(trap.depth_j(static), kt * scale_up * scale_down)
    return math.sqrt(p_extract * p_implant)


def move_survival(
    slot_duration_s: float, shape: str, sharpness: float, site_spacing_um: float, trap: TrapParameters
) -> tuple[float, float]:
    """``(p_transfer, p_step)`` from the speed of a slot alone; multiply by the speed-independent survivals."""
    if not slot_duration_s > 0 or not site_spacing_um > 0:
        raise ValueError(
            "move_survival needs a positive slot duration and site spacing "
            f"(got {slot_duration_s} s, {site_spacing_um} um)"
        )
    return (
        transfer_survival(slot_duration_s, shape, sharpness, trap),
        step_survival(slot_duration_s, shape, sharpness, site_spacing_um, trap),
    )
