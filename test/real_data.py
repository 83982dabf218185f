"""Where the real data sets of ../shared/data are: where an environment variable says,
else beside the repository, else in this machine's shared folder."""
from __future__ import annotations

import os
from pathlib import Path

BESIDE = Path(__file__).resolve().parents[2] / 'shared' / 'data'
SHARED = Path('/work/shared/data')


def shared_data(name: str, variable: str) -> Path:
    """The folder of the data set ``name`` (``$variable`` when set)."""
    if os.environ.get(variable):
        return Path(os.environ[variable])
    beside = BESIDE / name
    return beside if beside.is_dir() else SHARED / name


UR10_DATA = shared_data('ipa_ur10', 'IPA_UR10_DIR')
TIAGO_DATA = shared_data('tiago_mocap', 'TIAGO_MOCAP_DIR')
