"""Repository tooling: entry points run from the checkout (see README, "Layout"). The dataset builders import
the uninstalled data/ package, so they run from the repository root as modules: python -m scripts.build_dataset.
"""
