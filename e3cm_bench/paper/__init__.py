"""The paper's experiments, shipped inside the package: the experiment configs that
``e3cm-bench reproduce NAME`` runs (``configs/*.yaml``) and the numbers the paper reports
(``table1.csv`` .. ``table3.csv``), which tables and reports set beside the measured rows.

They are package data rather than files at the top of the checkout so that an install from
a wheel or an index has them: ``reproduce table1`` and the paper rows of ``report`` work
from any folder.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

# importlib.resources finds the data wherever the package is installed (a wheel in
# site-packages, an editable install, a checkout). Those are folders on disk, and the YAML
# and CSV readers take Paths, so the Traversable is taken as one.
PAPER_DIR = Path(str(resources.files(__name__)))
CONFIG_DIR = PAPER_DIR / "configs"


def config_names() -> dict[str, Path]:
    """Every shipped experiment config by name: the paper's short names first (``table1``,
    ``fig5``: a file name's part before the first ``_`` where no other config shares it),
    then every file's full stem (``table1_hpatches``, ``design_points_kitti``)."""
    paths = sorted(CONFIG_DIR.glob("*.yaml"))
    prefixes = [path.stem.split("_")[0] for path in paths]
    short = {
        prefix: path for prefix, path in zip(prefixes, paths) if prefixes.count(prefix) == 1 and prefix != path.stem
    }
    return {**short, **{path.stem: path for path in paths}}


def resolve_config(config: str | Path) -> Path:
    """An experiment config given as a path to a YAML file or as a shipped name (config_names).

    An existing file wins, so a user's own ``table1`` file is never shadowed by the package's.
    """
    path = Path(config)
    if path.is_file():
        return path
    names = config_names()
    if str(config) in names:
        return names[str(config)]
    raise FileNotFoundError(f"{config}: no such experiment config file, nor a known name ({', '.join(names)})")
