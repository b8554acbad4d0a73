"""The sequence-mode AWG card's rules, as the Spectrum M4i.66xx manual states them: one statement for every
place that must agree with the card.

The real adapter (``drivers/spectrum.py``) checks its uploads and steps against these rules before they
reach the card, the simulated AWG (``drivers/sim/awg.py``) refuses what the card would refuse, the card's
test fake (``tests/fake_spcm.py``) enforces them below the ``spcm`` package, and ``SystemConfig`` refuses a
waveform slot the card could not play when a configuration is applied. If the simulation were laxer than
the card, a configuration that runs in simulation would fail at the first upload in the lab.

Sources: the M4i.66xx manual, chapter "Sequence Mode" (tables "sequence mode registers for segment
handling", "sequence mode step registers and register setup"; the segment-size limits table for 16-bit
cards) and chapter "Data transfer" (page-aligned DMA buffers); Spectrum's own examples allocate every DMA
buffer 4 KiB aligned. The step-word masks are those of ``spcm_core.regs``.

Engine code, because the engine's configuration must be able to refuse a slot length (and the streamer
allocate DMA-ready buffers) without importing a driver; numbers and small functions only, no vendor software.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "BYTES_PER_SAMPLE",
    "CHANNEL_COUNTS",
    "DMA_ALIGN_BYTES",
    "SEGMENT_MIN_SAMPLES_1CH",
    "SEGMENT_STEP_SAMPLES",
    "SPCSEQ_END",
    "SPCSEQ_ENDLOOPALWAYS",
    "SPCSEQ_ENDLOOPONTRIG",
    "SPCSEQ_LOOPMASK",
    "SPCSEQ_NEXTSTEPMASK",
    "SPCSEQ_SEGMENTMASK",
    "decode_step",
    "encode_step",
    "max_segment_samples",
    "min_segment_samples",
    "page_aligned_zeros",
    "segment_length_problem",
    "segment_partition",
    "slot_length_problem",
]

#: Segment lengths are whole multiples of this many samples per channel (16-bit cards).
SEGMENT_STEP_SAMPLES = 32
#: The shortest segment with one channel enabled; with ``n`` channels it is ``384 / n`` (192, 96).
SEGMENT_MIN_SAMPLES_1CH = 384
#: The channel counts the card can enable at once (``SPC_CHENABLE``).
CHANNEL_COUNTS = (1, 2, 4)
#: int16 samples.
BYTES_PER_SAMPLE = 2
#: DMA buffers start on a memory page: the driver pins whole pages, Spectrum's examples align to 4 KiB.
DMA_ALIGN_BYTES = 4096

# One step is a 64-bit word at SPC_SEQMODE_STEPMEM0 + step. Low 32 bits: next_step << 16 | segment.
# High 32 bits: flags | loops.
SPCSEQ_SEGMENTMASK = 0x0000FFFF
SPCSEQ_NEXTSTEPMASK = 0xFFFF0000
SPCSEQ_LOOPMASK = 0x000FFFFF
SPCSEQ_ENDLOOPALWAYS = 0x00000000  # after `loops` passes go to next_step
SPCSEQ_ENDLOOPONTRIG = 0x40000000  # after `loops` passes repeat until a trigger has been seen
SPCSEQ_END = 0x80000000  # stop the card after this step


def min_segment_samples(n_channels: int) -> int:
    """The shortest segment the card plays with ``n_channels`` enabled (samples per channel)."""
    return SEGMENT_MIN_SAMPLES_1CH // n_channels


def segment_partition(n_segments: int) -> int:
    """``SPC_SEQMODE_MAXSEGMENTS`` for ``n_segments`` used segments: the card divides its memory into a power
    of two (at least 2) of equal segments."""
    partition = 2
    while partition < n_segments:
        partition *= 2
    return partition


def max_segment_samples(memory_bytes: int, n_channels: int, n_segments: int) -> int:
    """The longest segment (samples per channel) when ``memory_bytes`` is split for ``n_segments``."""
    per_segment = memory_bytes // (BYTES_PER_SAMPLE * n_channels * segment_partition(n_segments))
    return per_segment - per_segment % SEGMENT_STEP_SAMPLES


def segment_length_problem(n_samples: int, n_channels: int, max_samples: int | None = None) -> str | None:
    """Why the card refuses a segment of ``n_samples`` per channel, or ``None`` if it accepts it."""
    low = min_segment_samples(n_channels)
    if n_samples % SEGMENT_STEP_SAMPLES:
        return f"{n_samples} samples per channel is not a multiple of {SEGMENT_STEP_SAMPLES}"
    if n_samples < low:
        return f"{n_samples} samples per channel is below the card's minimum of {low} with {n_channels} channel(s)"
    if max_samples is not None and n_samples > max_samples:
        return f"{n_samples} samples per channel is above the {max_samples} one segment of the memory holds"
    return None


def segment_samples_problem(index: int, samples: object, n_segments: int, n_channels: int) -> str | None:
    """Why ``samples`` cannot be written into segment ``index`` of a card with ``n_segments`` segments and
    ``n_channels`` enabled channels (its index, or its array's type or shape), or ``None``. Its length is
    ``segment_length_problem``'s."""
    if not 0 <= index < n_segments:
        return f"segment index {index} out of range 0..{n_segments - 1}"
    if not isinstance(samples, np.ndarray) or samples.dtype != np.int16 or samples.ndim != 2 \
            or samples.shape[1] != n_channels:
        got = f"{samples.dtype} of shape {samples.shape}" if isinstance(samples, np.ndarray) else type(samples).__name__
        return f"segment {index}: samples must be int16[n, {n_channels}], got {got}"
    return None


def step_problem(index: int, segment: int, next_step: int, loops: int, n_steps: int, n_segments: int) -> str | None:
    """Why step ``index`` cannot be written with these fields on a card of ``n_steps`` steps and ``n_segments``
    segments (an index out of range, a loop count the step word cannot hold), or ``None``."""
    if not 0 <= index < n_steps:
        return f"step index {index} out of range 0..{n_steps - 1}"
    if not 0 <= segment < n_segments:
        return f"step {index}: segment {segment} out of range 0..{n_segments - 1}"
    if not 0 <= next_step < n_steps:
        return f"step {index}: next_step {next_step} out of range 0..{n_steps - 1}"
    if not 1 <= loops <= SPCSEQ_LOOPMASK:
        return f"step {index}: loops must be 1..{SPCSEQ_LOOPMASK} (the step word's loop field), got {loops}"
    return None


def slot_length_problem(sample_rate_hz: float, slot_duration_s: float, n_channels: int) -> str | None:
    """Why the card cannot play segments made of waveform slots of this length, with the fix; ``None`` if it can.

    The engine writes segments of whole slots, and one slot alone must be a valid segment (the short path
    and the failsafes are one slot long), so the slot itself must be a multiple of 32 samples.
    """
    n = round(sample_rate_hz * slot_duration_s)
    low = min_segment_samples(n_channels)
    if n < low:
        return (
            f"waveforms.slot_duration_s x waveforms.sample_rate_hz = {n} samples, below the card's shortest segment "
            f"of {low} samples with {n_channels} channel(s): make the slot at least {low / sample_rate_hz * 1e6:.6g} us"
        )
    if n % SEGMENT_STEP_SAMPLES == 0:
        return None
    below = n - n % SEGMENT_STEP_SAMPLES
    lengths = [m for m in (below, below + SEGMENT_STEP_SAMPLES) if m > 0]
    rates = " or ".join(f"{m / slot_duration_s / 1e6:.6g} MS/s" for m in lengths)
    slots = " or ".join(f"{m / sample_rate_hz * 1e6:.6g} us" for m in lengths)
    return (
        f"waveforms.slot_duration_s x waveforms.sample_rate_hz = {slot_duration_s * 1e6:g} us x "
        f"{sample_rate_hz / 1e6:g} MS/s = {n} samples, but the card plays segments in multiples of "
        f"{SEGMENT_STEP_SAMPLES} samples: use sample_rate_hz {rates} (same slot, same tone grid), or "
        f"slot_duration_s {slots}"
    )


def page_aligned_zeros(shape: int | tuple[int, ...], dtype: np.dtype | type = np.int16) -> np.ndarray:
    """A zeroed C-contiguous array whose data start on a ``DMA_ALIGN_BYTES`` boundary (numpy's allocator
    gives no such promise), so the card can DMA from it in place."""
    dt = np.dtype(dtype)
    nbytes = int(np.prod(shape)) * dt.itemsize
    raw = np.zeros(nbytes + DMA_ALIGN_BYTES, dtype=np.uint8)
    start = -raw.ctypes.data % DMA_ALIGN_BYTES
    return raw[start : start + nbytes].view(dt).reshape(shape)


def encode_step(segment: int, next_step: int, loops: int = 1, *, on_trigger: bool = False, end: bool = False) -> int:
    """The 64-bit step word: play ``segment`` ``loops`` times, then go to ``next_step``."""
    flags = (SPCSEQ_ENDLOOPONTRIG if on_trigger else SPCSEQ_ENDLOOPALWAYS) | (SPCSEQ_END if end else 0)
    low = ((next_step << 16) & SPCSEQ_NEXTSTEPMASK) | (segment & SPCSEQ_SEGMENTMASK)
    return ((flags | (loops & SPCSEQ_LOOPMASK)) << 32) | low


def decode_step(word: int) -> dict[str, int | bool]:
    """Inverse of ``encode_step``: the fields of a step word, straight from the manual's table."""
    word &= (1 << 64) - 1
    high = word >> 32
    return {
        "segment": word & SPCSEQ_SEGMENTMASK,
        "next_step": (word & SPCSEQ_NEXTSTEPMASK) >> 16,
        "loops": high & SPCSEQ_LOOPMASK,
        "on_trigger": bool(high & SPCSEQ_ENDLOOPONTRIG),
        "end": bool(high & SPCSEQ_END),
    }
