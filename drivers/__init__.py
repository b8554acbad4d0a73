"""Adapters that implement the engine's device protocols: the simulated lab (``drivers.sim``) and, later,
the vendor hardware. Vendor modules are imported lazily inside ``open()`` so nothing here needs them."""
