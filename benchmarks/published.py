"""Published ATE figures on the TUM RGB-D benchmark, to print beside our measured ones.

These are the papers' own numbers (absolute trajectory error RMSE, metres, over the whole
sequence), not measured here: other machines, their own settings, full SLAM systems with loop
closure or bundle adjustment. A dash where a paper did not report the sequence.
"""

from __future__ import annotations

import re

PAPERS = {
    "DVO-SLAM": "Kerl, Sturm, Cremers: Dense Visual SLAM for RGB-D Cameras, IROS 2013, Table I",
    "ORB-SLAM2": "Mur-Artal, Tardos: ORB-SLAM2, IEEE T-RO 2017, Table III (RGB-D)",
    "ElasticFusion": "Whelan et al.: ElasticFusion, RSS 2015, Table 2",
}

# sequence -> paper -> ATE RMSE in metres
ATE_M: dict[str, dict[str, float]] = {
    "fr1/xyz": {"DVO-SLAM": 0.011},
    "fr1/rpy": {"DVO-SLAM": 0.020},
    "fr1/desk": {"DVO-SLAM": 0.021, "ORB-SLAM2": 0.016, "ElasticFusion": 0.020},
    "fr1/desk2": {"DVO-SLAM": 0.046, "ORB-SLAM2": 0.022},
    "fr1/room": {"DVO-SLAM": 0.053, "ORB-SLAM2": 0.047},
    "fr1/360": {"DVO-SLAM": 0.083},
    "fr2/xyz": {"DVO-SLAM": 0.018, "ORB-SLAM2": 0.004, "ElasticFusion": 0.011},
    "fr2/desk": {"DVO-SLAM": 0.017, "ORB-SLAM2": 0.009},
    "fr3/office": {"DVO-SLAM": 0.035, "ORB-SLAM2": 0.010, "ElasticFusion": 0.017},
}


def tum_sequence(name: str) -> str | None:
    """'fr1/desk' for a folder named like tum_fr1_desk, rgbd_dataset_freiburg1_desk or
    fr1_desk (a trailing _validation or similar is ignored); None for anything else."""
    m = re.search(r"(?:freiburg|fr)(\d)[_/-]([a-z0-9]+(?:_?[0-9]+)?)", name.lower())
    if m is None:
        return None
    seq = f"fr{m.group(1)}/{m.group(2)}"
    # fr3/long_office_household is reported as fr3/office
    return "fr3/office" if seq.startswith("fr3/long") else seq


def published(name: str) -> dict[str, float]:
    """The published ATE RMSE (metres) per paper for sequence folder ``name``; {} if none."""
    seq = tum_sequence(name)
    return dict(ATE_M.get(seq, {})) if seq else {}
