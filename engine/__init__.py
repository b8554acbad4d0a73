"""The LLRS domain: configuration, imaging, solvers, waveforms, streaming and the engine thread.

No web framework and no vendor SDK is imported here; devices are reached through the protocols in
``engine.devices``.
"""
