"""Repository tooling: entry points run from the checkout (see README, "Layout"). The dataset builders import
the uninstalled data/ package: they put the checkout on sys.path, so `python scripts/build_dataset.py` and
`python -m scripts.build_dataset` both work from the repository root.
"""
