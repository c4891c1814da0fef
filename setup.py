"""Ships the Hydra configs (`conf/`) inside the distribution as the package `mousetrack_conf`,
so that a non-editable install (`pip install .`) has them; everything else is in
pyproject.toml."""

from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["deformnet*", "adjust*"]), "mousetrack_conf"],
    package_dir={"mousetrack_conf": "conf"},
    package_data={
        "mousetrack_conf": ["*.yaml", "**/*.yaml"],
        "deformnet.pretrained": ["*.pt"],  # the shipped default net
    },
)
