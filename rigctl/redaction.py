"""Secrets kept out of what rigctl writes: the service token redacted from the rig file's
copy in a run directory (``rig.yaml``), from JSON records, log lines and answers.

Pure text functions with no import of the rest of rigctl, so that the rig file's model
(``config``) and the records (``records``) both use them.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Any

import yaml

REDACTED = "<redacted>"
# a secret this short is only replaced where the rig file's own key holds it: replacing
# every occurrence of a few characters would garble the copy
MIN_LITERAL = 6


def redact_text(text: str, hidden: Iterable[str]) -> str:
    """``text`` with every occurrence of each secret (``MIN_LITERAL`` characters or
    more) replaced by ``REDACTED``."""
    for secret in sorted({s for s in hidden if s and len(s) >= MIN_LITERAL}, key=len,
                         reverse=True):
        text = text.replace(secret, REDACTED)
    return text


def redact_rig_text(text: str, hidden: Iterable[str]) -> str:
    """The rig file's text as a run directory keeps it (``rig.yaml``): the value of
    ``service.token`` replaced by ``REDACTED`` whatever its YAML style, comments and
    layout kept, and any other occurrence of a secret replaced too (``redact_text``).
    The copy still loads (a re-solve reads it); its token is only a placeholder."""
    hidden = [s for s in hidden if s]
    node = _yaml_value(_yaml_value(_compose(text), "service"), "token")
    if isinstance(node, yaml.ScalarNode) and node.tag != "tag:yaml.org,2002:null":
        start, end = node.start_mark.index, node.end_mark.index
        tail = "\n" if text[start:end].endswith("\n") else ""
        text = f'{text[:start]}"{REDACTED}"{tail}{text[end:]}'
    return redact_text(text, hidden)


def _compose(text: str) -> yaml.Node | None:
    try:
        return yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return None


def _yaml_value(node: yaml.Node | None, key: str) -> yaml.Node | None:
    if not isinstance(node, yaml.MappingNode):
        return None
    for k, v in node.value:
        if isinstance(k, yaml.ScalarNode) and k.value == key:
            return v
    return None


def scrub(value: Any, hidden: Iterable[str]) -> Any:
    """``value`` (JSON-like: dicts, lists, strings) with each secret in its strings and
    keys replaced by ``REDACTED`` (``redact_text``)."""
    hidden = [s for s in hidden if s]
    if not hidden:
        return value
    if isinstance(value, str):
        return redact_text(value, hidden)
    if isinstance(value, dict):
        return {scrub(k, hidden): scrub(v, hidden) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [scrub(v, hidden) for v in value]
    return value


class RedactingFormatter(logging.Formatter):
    """A log formatter whose lines (message, arguments, traceback) never carry a secret:
    the run's ``run.log`` is written with it."""

    def __init__(self, fmt: str, hidden: Iterable[str]) -> None:
        super().__init__(fmt)
        self.hidden = [s for s in hidden if s]

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        for secret in self.hidden:  # a short secret too: a log line has no layout to keep
            text = text.replace(secret, REDACTED)
        return text
