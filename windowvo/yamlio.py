"""YAML in and out for every windowvo file: floats as a user writes them (3.4e2, 1e-3) on reading,
plain Python numbers (never numpy scalars) on writing."""

from __future__ import annotations

import re
from typing import Any

import numpy as np
import yaml

FLOAT_TAG = "tag:yaml.org,2002:float"
# YAML 1.1 (PyYAML) floats need a dot and a signed exponent: 3.4e2 and 1e-3 would load as strings.
# This accepts every spelling of YAML 1.2 and Python as well (340.0, 3.4e2, 3.4E+2, 1e-3, .5, -.5e3),
# keeps 1_000.5, .inf and .nan, and leaves integers (340, 0x1F) to the integer resolver.
FLOAT_PATTERN = re.compile(
    r"""^(?:[-+]?[0-9][0-9_]*\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+
    |[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]*
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""", re.X)


class _NumberLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` with :data:`FLOAT_PATTERN` as its float resolver."""


_NumberLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag != FLOAT_TAG]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_NumberLoader.add_implicit_resolver(FLOAT_TAG, FLOAT_PATTERN, list("-+0123456789."))


def safe_load_yaml(text: str) -> Any:
    """``yaml.safe_load`` that reads every float spelling a user writes (3.4e2, 3.4E+2, 1e-3) as a float.

    Raises ``yaml.YAMLError`` like ``yaml.safe_load``; integers, strings and the rest are unchanged.
    """
    return yaml.load(text, Loader=_NumberLoader)  # a SafeLoader subclass: safe


def plain(value: Any) -> Any:
    """``value`` with numpy scalars and arrays turned into Python numbers and lists (recursively through
    dicts, lists and tuples), so that ``yaml.safe_dump`` can write it."""
    if isinstance(value, dict):
        return {plain(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    return value


def dump_yaml(data: Any, **kwargs: Any) -> str:
    """``yaml.safe_dump`` of ``data`` after :func:`plain` (keys keep their order unless ``sort_keys``)."""
    kwargs.setdefault("sort_keys", False)
    return yaml.safe_dump(plain(data), **kwargs)
