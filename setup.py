"""Package discovery for pyproject.toml, which holds everything else.

Three folders install under namespaced names (DESIGN.md): ``physint_cli``, ``backends`` as
``physint_backends`` and ``plugins`` as ``physint_plugins``. pyproject.toml's own package finder
cannot rename a folder, so the packages are found here: a new plugin folder with an
``__init__.py`` is packaged as it is, and needs only its entry-point line in pyproject.toml.
"""

from setuptools import find_packages, setup

FOLDERS = {"physint_cli": "physint_cli", "physint_backends": "backends", "physint_plugins": "plugins"}

setup(
    package_dir=FOLDERS,
    packages=[name for name in FOLDERS]
    + [f"{name}.{sub}" for name, folder in FOLDERS.items() for sub in find_packages(folder)],
)
