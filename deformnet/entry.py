"""deformnet's console scripts (pyproject.toml): a bare ``--help`` without importing the app
(`deformnet.quickhelp`), else the app's Hydra entry point."""

from deformnet.quickhelp import console_script

simulate = console_script("simulate", "deformnet.apps.simulate:main")
train = console_script("train", "deformnet.apps.train:main")
classify = console_script("classify", "deformnet.apps.classify:main")
