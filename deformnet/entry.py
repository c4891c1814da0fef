"""deformnet's console scripts (pyproject.toml): a bare ``--help`` without importing the app
(`deformnet.quickhelp`), else the app's Hydra entry point."""

from deformnet.quickhelp import console_script

simulate = console_script("simulate", "deformnet.sim.cli:main")
train = console_script("train", "deformnet.train:main")
classify = console_script("classify", "deformnet.classify:main")
