"""dfvo.validation: the one home of the settings checks (choices, checks, typed nodes), importable from every layer."""

from __future__ import annotations

import ast
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

import pytest
from omegaconf import OmegaConf

import dfvo.validation as validation
from dfvo.validation import check, choice, one_of, positive, typed


class Colour(StrEnum):
    red = "red"
    green = "green"


@dataclass
class _Node:
    colour: Colour = Colour.red
    size: int = 3

    def __post_init__(self) -> None:
        self.colour = choice(Colour, self.colour, "node.colour")
        positive("node", size=self.size)


def test_choice_returns_the_member_or_names_the_setting_and_the_values() -> None:
    assert choice(Colour, "green", "x.colour") is Colour.green
    assert choice(Colour, Colour.red, "x.colour") is Colour.red
    with pytest.raises(ValueError, match=r"^x.colour='blue'; expected one of \['red', 'green'\]$"):
        choice(Colour, "blue", "x.colour")
    assert one_of(("kitti", "tum"), "tum", "format") == "tum"
    with pytest.raises(ValueError, match=r"^format='csv'; expected one of \['kitti', 'tum'\]$"):
        one_of(("kitti", "tum"), "csv", "format")


def test_check_and_positive() -> None:
    check(True, "never raised")
    with pytest.raises(ValueError, match="^a.b=0; expected > 0$"):
        check(False, "a.b=0; expected > 0")
    positive("data", height=1, width=None)
    with pytest.raises(ValueError, match=r"^data.width=-2; expected > 0$"):
        positive("data", height=1, width=-2)


def test_typed_builds_the_dataclass_and_reports_one_line() -> None:
    assert typed({"colour": "green"}, _Node) == _Node(Colour.green, 3)
    assert typed(OmegaConf.structured(_Node(size=5))) == _Node(Colour.red, 5)
    with pytest.raises(ValueError, match=r"^node.size=0; expected > 0$"):
        typed({"size": 0}, _Node, "node")  # the __post_init__ check itself, not OmegaConf's wrapper of it
    with pytest.raises(ValueError, match=r"^node.colour: Invalid value 'blue', expected one of \[red, green\]$"):
        typed({"colour": "blue"}, _Node, "node")  # OmegaConf checks an enum field while merging
    with pytest.raises(ValueError, match=r"node.*sise") as err:
        typed({"sise": 4}, _Node, "node")  # an unknown key
    assert "\n" not in str(err.value)


def test_the_validation_module_imports_nothing_from_dfvo() -> None:
    """It sits below every layer: any dfvo import there could close an import cycle."""
    tree = ast.parse(Path(validation.__file__).read_text())
    imported = [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    imported += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    assert not [m for m in imported if m == "dfvo" or m.startswith("dfvo.")]


def test_the_settings_use_it() -> None:
    """The former private copies are gone: one typed(), one choice helper."""
    import dfvo.cli.evaluate as cli_evaluate
    import dfvo.inference.config as infer_config
    import dfvo.tracking.config as tracker_config
    import dfvo.training.config as train_config

    assert infer_config.typed is train_config.typed is typed
    assert not hasattr(tracker_config, "_choice") and not hasattr(cli_evaluate, "_choice")
