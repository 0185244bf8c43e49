"""Build hook: the packages, and the presets of ``state_files/`` as ``dvr_perception/state_files``.

Everything else is in ``pyproject.toml``.  The presets (structure specs paired with the shared
volumes) stay in the repository's top-level ``state_files/``; the wheel carries their ``.json``
files inside the package, where :func:`dvr_perception._resources.state_files_dir` finds them.
The ParaView state scripts of that folder (``*_state.py``) stay out: they load the plugin of a
checkout.
"""

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

PRESETS = "dvr_perception.state_files"


class BuildPy(build_py):
    """``build_py`` that takes only the ``.json`` data of the presets folder, no modules."""

    def find_package_modules(self, package, package_dir):
        """Return the modules of ``package``; none for the presets folder."""
        if package == PRESETS:
            return []
        return super().find_package_modules(package, package_dir)


setup(
    packages=[*find_packages(include=["dvr_perception", "dvr_perception.*"]), PRESETS],
    package_dir={PRESETS: "state_files"},
    cmdclass={"build_py": BuildPy},
)
