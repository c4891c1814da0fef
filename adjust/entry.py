"""adjust's console scripts (pyproject.toml): a bare ``--help`` without importing the app
(`deformnet.quickhelp`), else the app's Hydra entry point."""

from deformnet.quickhelp import console_script

simulate = console_script("scene", "adjust.scene_cli:main")
triangulate = console_script("triangulate", "adjust.triangulate_cli:main")
track = console_script("track", "adjust.track:main")
calibrate = console_script("calibrate", "adjust.calibrate_cli:main")
events = console_script("events", "adjust.events_cli:main")
export = console_script("export", "adjust.export_cli:main")
demo = console_script("demo", "adjust.demo:main")
plot = console_script("plot", "adjust.plot_cli:main")
