"""adjust's console scripts (pyproject.toml): a bare ``--help`` without importing the app
(`deformnet.quickhelp`), else the app's Hydra entry point."""

from deformnet.quickhelp import console_script

simulate = console_script("scene", "adjust.apps.simulate:main")
triangulate = console_script("triangulate", "adjust.apps.triangulate:main")
track = console_script("track", "adjust.apps.track:main")
calibrate = console_script("calibrate", "adjust.apps.calibrate:main")
events = console_script("events", "adjust.apps.events:main")
export = console_script("export", "adjust.apps.export:main")
demo = console_script("demo", "adjust.apps.demo:main")
plot = console_script("plot", "adjust.apps.plot:main")
