"""The classifier's benchmarks, the parts it adds to ``torchdoct bench`` through the entry-point table
(:mod:`torchdoct.cli.extensions`; torchdoct never imports them by name): :mod:`.classify` (``torchdoct bench
classify``: classify-path throughput) and :mod:`.tradeoffs` (``torchdoct bench tradeoffs --part
classifier``: what accuracy costs in time)."""
