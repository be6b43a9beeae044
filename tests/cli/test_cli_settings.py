"""Training settings have one declaration: the config dataclasses. A command's option for a TrainConfig,
PPOConfig, EngineConfig or RunBudget field is generated from that field (navi/commands/options.py), so its name,
default and help come from the dataclass; no command declares such an option by hand."""

from __future__ import annotations

import functools
from collections.abc import Iterator
from dataclasses import MISSING, fields
from typing import Any

import typer
from typer.testing import CliRunner

from navi.cli import build_app
from navi.commands.options import Setting, config_fields, field_docs, generated_settings
from navi_learner.config import EngineConfig, PPOConfig, RunBudget, TrainConfig, learning_recipe

FIELDS = set(config_fields(TrainConfig)) | set(config_fields(RunBudget))
"""Every scalar setting of TrainConfig, its PPOConfig and its EngineConfig, and of `navi run`'s RunBudget."""

CONTEXT = {"device", "seed", "task", "total_steps"}
"""Settings that commands which train nothing (evaluation, serving an env, benchmarks of a stage) take for
themselves: their device, their seed, the task they fly and how many steps they run."""

TRAINING_COMMANDS = {"train", "bench learn", "bench transfer", "bench train", "serve learner", "bc", "run"}

OTHER_CONFIGS = {("bc", "lr")}
"""Options of another config that share a field's name: `navi bc --lr` is BCConfig.lr (behavioural cloning)."""


def commands() -> Iterator[tuple[str, Any]]:
    """(name, click command) of every registered command, sub-commands by their full name."""

    def walk(prefix: str, group: Any) -> Iterator[tuple[str, Any]]:
        if hasattr(group, "commands"):  # a group
            for name, cmd in group.commands.items():
                yield from walk(f"{prefix} {name}".strip(), cmd)
        else:
            yield prefix, group

    yield from walk("", typer.main.get_command(build_app()))


def generated(cmd: Any) -> dict[str, Setting]:
    assert cmd.callback is not None
    return dict(generated_settings(cmd.callback))


def field_default(setting: Setting) -> object:
    """The default the dataclass declares for the setting's field."""
    f = next(f for f in fields(setting.owner) if f.name == setting.name)
    if f.default is not MISSING:
        return f.default
    assert f.default_factory is not MISSING
    return f.default_factory()


def test_the_training_commands_generate_their_settings() -> None:
    found = {name for name, cmd in commands() if generated(cmd)}
    assert found == TRAINING_COMMANDS
    train = dict(commands())["train"]
    assert {"lr", "ppo_epochs", "max_minibatch", "target_kl", "temporal_core", "n_actors"} <= set(
        generated(train)
    )


def test_no_command_declares_a_config_setting_by_hand() -> None:
    """A hand-written option named after a config field would be a second declaration with its own default.
    Commands that build a TrainConfig generate every such option; the others may take only the CONTEXT
    ones."""
    shadows = []
    for name, cmd in commands():
        mine = generated(cmd)
        hand = {p.name for p in cmd.params if p.name is not None and p.name not in mine}
        trains = isinstance(getattr(cmd.callback, "__settings_base__", None), TrainConfig)
        allowed = set() if trains else CONTEXT
        hand -= {p for n, p in OTHER_CONFIGS if n == name}
        shadows += [f"navi {name}: {p}" for p in sorted(hand & (FIELDS - allowed))]
        for param, setting in mine.items():
            assert param == setting.name and param in FIELDS, (name, param)
    assert not shadows, f"options declared by hand that shadow config fields: {shadows}"


def test_generated_defaults_are_the_dataclass_defaults() -> None:
    """Each generated option's default is its field's default; a command departs from it only by name: its
    own `defaults` (--device auto) or a named recipe as its base (bench learn: learning_recipe)."""
    recipe = learning_recipe()
    for name, cmd in commands():
        mine = generated(cmd)
        base = getattr(cmd.callback, "__settings_base__", None)
        for p in cmd.params:
            if p.name not in mine:
                continue
            setting = mine[p.name]
            assert p.default == setting.default, (name, p.name)
            if setting.own_default:
                assert (setting.name, setting.default) == ("device", "auto"), (name, setting)
                continue
            declared = field_default(setting)
            if base == recipe:
                declared = functools.reduce(getattr, setting.path, recipe)
            else:
                assert base in (TrainConfig(), EngineConfig(), RunBudget()), name
            assert setting.default == declared, (name, p.name, setting.default, declared)


def test_the_learning_recipe_is_named_departures_from_the_defaults() -> None:
    recipe = learning_recipe()
    bench = dict(commands())["bench learn"]
    options = {p.name: p.default for p in bench.params}
    assert (options["lr"], options["ppo_epochs"], options["max_minibatch"]) == (
        recipe.ppo.lr,
        recipe.ppo.ppo_epochs,
        recipe.ppo.max_minibatch,
    )
    train = {p.name: p.default for p in dict(commands())["train"].params}
    assert (train["lr"], train["ppo_epochs"], train["max_minibatch"]) == (
        PPOConfig().lr,
        PPOConfig().ppo_epochs,
        PPOConfig().max_minibatch,
    )


def test_generated_help_is_the_field_docstring() -> None:
    for name, cmd in commands():
        mine = generated(cmd)
        for p in cmd.params:
            if p.name in mine and not mine[p.name].own_help:
                setting = mine[p.name]
                doc = field_docs(setting.owner)[setting.name]
                assert doc, (name, p.name)
                assert p.help == doc.replace("[", "\\["), (name, p.name)
    shown = CliRunner().invoke(build_app(), ["train", "--help"], env={"COLUMNS": "400"})
    assert shown.exit_code == 0, shown.output
    assert field_docs(PPOConfig)["ppo_epochs"] in shown.output
    assert "within [lr_min, lr_max]" in shown.output  # brackets of a docstring are text, not markup


def test_bools_are_flag_pairs_and_flags_follow_the_field_or_its_cli_option() -> None:
    train = dict(commands())["train"]
    opts = {p.name: p for p in train.params}
    assert opts["compile_update"].opts == ["--compile-update"]
    assert opts["compile_update"].secondary_opts == ["--no-compile-update"]
    assert opts["n_actors"].opts == ["--actors"] and opts["obs_dtype"].opts == ["--obs-storage"]
    assert opts["target_kl"].opts == ["--target-kl"]
