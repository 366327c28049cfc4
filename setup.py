"""Packaging for torch_polylap (pure Python; torch is a runtime dependency only)."""

import re
from pathlib import Path

from setuptools import find_packages, setup

HERE = Path(__file__).parent
# one version, written once: torch_polylap.__version__
VERSION = re.search(
    r'^__version__ = "([^"]+)"', (HERE / "torch_polylap" / "__init__.py").read_text(), re.M
)[1]

setup(
    name="torch_polylap",
    version=VERSION,
    description=(
        "Differentiable Alexa-Wardetzky discrete Laplacian on general polygon meshes for PyTorch"
    ),
    long_description=(HERE / "README.md").read_text(encoding="utf-8"),
    long_description_content_type="text/markdown",
    license="MIT",
    python_requires=">=3.10",
    packages=find_packages(include=["torch_polylap", "torch_polylap.*"]),
    # the console script's entry: it catches Ctrl-C during the package's imports too
    py_modules=["_polylap_launcher"],
    package_data={"torch_polylap": ["data/*.obj", "data/*.md", "py.typed"]},
    # tqdm: progress bars on the iterative applications (flow, planarization); pure Python, tiny
    # torch 2.13: the oldest release the test suite passes on. The eager operators need only
    # 2.5 (custom ops with vmap and autocast rules), but torch.compile's handling of the
    # operator type changed until 2.13: on 2.12 every compiled step fails, on 2.7 torch.func's
    # forward mode too. CI runs the tests on 2.13.0 and on the newest release it can install
    # (see docs/getting-started.md).
    install_requires=[
        "torch>=2.13",
        "numpy>=1.22",
        "scipy>=1.9",
        "trimesh>=3.20",
        "tqdm>=4.60",
        # threadpoolctl: one BLAS/OpenMP thread in each precompute worker (pure Python)
        "threadpoolctl>=3.1",
    ],
    extras_require={
        # libigl: the independent cotan Laplacian the tests and benchmarks compare against
        # matplotlib: the figures the command line and the examples write
        # cholespy: CHOLMOD's supernodal Cholesky, the fast factorization behind eigs
        # qdldl: QDLDL's L D L^T, the heat geodesic solver's factorization (tests compare both)
        # hypothesis: the property-based tests of the mesh readers and writers
        # pyarrow: the fast-text number conversion, which the tests check against Python's
        # adobe-lagrange: de Goes et al. 2020's operators (polyddg), the dGBD20 reference (wheel)
        # torch_geometric: the real Data/Batch that tests/test_interop.py checks to_pyg/from_pyg
        # against (pure Python; its compiled extensions are not needed)
        "test": [
            "pytest>=7",
            # build: CI builds the sdist and the wheel from it and installs that (.ci/package)
            "build>=1.0",
            "ruff>=0.4",
            "mypy>=2.4",  # .ci/run type-checks torch_polylap (config in pyproject.toml)
            "libigl>=2.5",
            "matplotlib>=3.5",
            "cholespy>=2.0",
            "qdldl>=0.1.9",
            "hypothesis>=6",
            "pyarrow>=14",
            "adobe-lagrange>=6.49",
            "torch_geometric>=2.3",
        ],
        "cholmod": ["cholespy>=2.0"],
        # pyarrow: converts the numbers of ASCII OBJ, OFF and PLY files several times faster
        # than numpy, to the same correctly rounded values (numpy's parser without it)
        "fast-text": ["pyarrow>=14"],
        # qdldl: QDLDL's sparse L D L^T (AMD ordering), the heat geodesic solver's factorization
        "ldl": ["qdldl>=0.1.9"],
        # mkdocs + mkdocstrings-python: the documentation site (docs/, mkdocs.yml), whose API
        # reference is generated from the docstrings (2.0: the griffe extension API that
        # docs/griffe_roles.py uses); CI builds it with --strict
        "docs": ["mkdocs>=1.6", "mkdocstrings-python>=2.0"],
        "plot": ["matplotlib>=3.5"],
        # dask's distributed: the dataset precompute on a cluster (polylap precompute
        # --scheduler); optional, as it pulls tornado, msgpack and a dozen more packages that a
        # single-machine user never needs. The cache itself is numpy's .npz (allow_pickle=False,
        # a SHA-256 per entry): numpy is a dependency already, so no format package is needed
        "distributed": ["dask[distributed]>=2024.1"],
        # potpourri3d: the polygon heat-method peer of benchmarks/bench_geodesics.py
        "bench": [
            "libigl>=2.5",
            "matplotlib>=3.5",
            "cholespy>=2.0",
            "qdldl>=0.1.9",
            "robust-laplacian",
            "potpourri3d",
        ],
    },
    entry_points={"console_scripts": ["polylap=_polylap_launcher:main"]},
    classifiers=[
        "Programming Language :: Python :: 3",
        "Topic :: Scientific/Engineering :: Mathematics",
        "Intended Audience :: Science/Research",
    ],
)
