"""The YAML style of the calibration and covariance files: plain values, one dumper.

Block style, except flow style for lists and for mappings of scalars only; numpy scalars and
arrays become plain Python values first.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from typing import Any

import numpy as np
import yaml

__all__ = ["Dumper", "plain"]


def plain(x: Any) -> Any:
    """Convert numpy scalars / arrays and tuples into plain Python (YAML-safe) values."""
    if isinstance(x, Mapping):
        return {str(k): plain(v) for k, v in x.items()}
    if isinstance(x, np.ndarray):
        return [plain(v) for v in x.reshape(-1).tolist()] if x.ndim else plain(x.item())
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, numbers.Integral):
        return int(x)
    if isinstance(x, numbers.Real):
        return float(x)
    return x


class Dumper(yaml.SafeDumper):
    """Block style, except flow style for lists and for mappings of scalars only."""


def _represent_list(dumper: yaml.SafeDumper, data: list[Any]) -> yaml.Node:
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=True)


def _represent_dict(dumper: yaml.SafeDumper, data: dict[str, Any]) -> yaml.Node:
    flow = all(not isinstance(v, (dict, list)) for v in data.values())
    return dumper.represent_mapping("tag:yaml.org,2002:map", data, flow_style=flow)


Dumper.add_representer(list, _represent_list)
Dumper.add_representer(dict, _represent_dict)
