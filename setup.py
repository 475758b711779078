"""Package discovery for holowarp.

Everything else lives in ``pyproject.toml``. This file exists only because the
``kernels/`` folder at the repository root installs as ``holowarp.kernels``
(and ``scenes/`` as ``holowarp.scenes``) through a package-dir mapping, and the
subpackage list has to be computed so that new subpackages need no edit here.
No top-level ``kernels`` module ever lands in site-packages.
"""

from setuptools import find_packages, setup

packages = find_packages(include=["holowarp", "holowarp.*"])
packages += ["holowarp.kernels"] + ["holowarp.kernels." + p for p in find_packages("kernels")]
packages += ["holowarp.scenes"]

setup(
    packages=packages,
    package_dir={"holowarp.kernels": "kernels", "holowarp.scenes": "scenes"},
    package_data={
        "holowarp": ["assets/*/*"],
        "holowarp.scenes": ["*.toml"],
    },
)
