"""Build hook: the packages, and the presets of ``state_files/`` as ``dvr_perception/state_files``.

Everything else is in ``pyproject.toml``.  The presets (structure specs paired with the shared
volumes) stay in the repository's top-level ``state_files/``; the wheel carries their ``.json``
files inside the package, where :func:`dvr_perception._resources.state_files_dir` finds them.
"""

from setuptools import find_packages, setup

setup(
    packages=[
        *find_packages(include=["dvr_perception", "dvr_perception.*"]),
        "dvr_perception.state_files",
    ],
    package_dir={"dvr_perception.state_files": "state_files"},
)
