"""deformnet's console scripts, one thin module each over a library `run(cfg)`; the library
never imports them (tests/test_layering.py)."""
