"""adjust's console scripts, one thin module each over a plain ``run(cfg)`` (``adjust/entry.py``
and pyproject.toml name them): `simulate`, `triangulate`, `track` (and its batches, `batch`),
`calibrate`, `events`, `export`, `plot`, `demo` (with its `report`); `common` is what they share.
The library (the rest of `adjust`) never imports an app (tests/test_layering.py)."""
