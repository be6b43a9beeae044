"""Command options generated from config dataclasses: one declaration per setting.

`config_options(base, names)` turns fields of a config dataclass (and of the dataclasses nested in it,
e.g. TrainConfig's `ppo` and `engine`) into typer options of a command: the option is `--field-name`
(`--x/--no-x` for a bool; a `CliOption` in the field's annotation may rename or bound it), its type is
the field's, its default the field's value in `base` and its help the field's docstring (the string
literal right after the field in the class body). The command function takes one `settings: Settings`
parameter where the generated options go; `settings.config()` is `base` with their values. Module-level
imports: typer, the standard library and the torch-free navi_learner.config.
"""

from __future__ import annotations

import ast
import functools
import inspect
import itertools
import textwrap
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields, is_dataclass, replace
from typing import Annotated, Any, Literal, TypeVar, get_args, get_origin, get_type_hints

import typer

from navi_learner.config import CliOption

F = TypeVar("F", bound=Callable[..., Any])

SETTINGS_PARAMETER = "settings"
"""The command function's parameter that receives the generated options (a Settings)."""


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """Each documented field of dataclass `cls`: its docstring with the whitespace collapsed."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = next(node for node in tree.body if isinstance(node, ast.ClassDef)).body
    docs: dict[str, str] = {}
    for stmt, after in itertools.pairwise(body):
        if not (isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name)):
            continue
        text = (
            after.value.value
            if isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
            else None
        )
        if isinstance(text, str):
            docs[stmt.target.id] = " ".join(text.split())
    return docs


@dataclass(frozen=True)
class Setting:
    """One generated option: the field it comes from and what the command shows of it."""

    owner: type
    """The dataclass that declares the field."""
    path: tuple[str, ...]
    """Attribute path from the base config to the field, e.g. ("ppo", "lr")."""
    kind: type
    """int, float, bool or str."""
    default: Any
    help: str
    flag: str
    """The option's name, e.g. --lr (for a bool: --x/--no-x)."""
    min: float | None = None
    max: float | None = None
    own_default: bool = False
    """The command gives its own default (not the base config's value)."""
    own_help: bool = False
    """The command gives its own help (not the field's docstring)."""

    @property
    def name(self) -> str:
        """The field's (and the command parameter's) name."""
        return self.path[-1]


def _base_type(hint: Any) -> tuple[type, tuple[Any, ...]]:
    """(int | float | bool | str, Annotated metadata) of a field's type; a Literal of strings is str."""
    extras: tuple[Any, ...] = ()
    if get_origin(hint) is Annotated:
        hint, *rest = get_args(hint)
        extras = tuple(rest)
    if get_origin(hint) is Literal:
        hint = type(get_args(hint)[0])
    if hint not in (int, float, bool, str):
        raise TypeError(f"no command option for a field of type {hint!r}")
    return hint, extras


def config_fields(cls: type, prefix: tuple[str, ...] = ()) -> dict[str, tuple[type, tuple[str, ...], Any]]:
    """Every scalar field of `cls` and of the dataclasses nested in it: name -> (owner, path, type hint)."""
    hints = get_type_hints(cls, include_extras=True)
    out: dict[str, tuple[type, tuple[str, ...], Any]] = {}
    for f in fields(cls):
        hint = hints[f.name]
        if isinstance(hint, type) and is_dataclass(hint):
            nested = config_fields(hint, (*prefix, f.name))
            if set(nested) & set(out):
                raise ValueError(f"{cls.__name__}: field names repeat in {hint.__name__}")
            out |= nested
        else:
            out[f.name] = (cls, (*prefix, f.name), hint)
    return out


def settings_of(
    base: Any, names: tuple[str, ...], defaults: Mapping[str, Any], helps: Mapping[str, str]
) -> dict[str, Setting]:
    """The Setting of each field in `names` of `base`'s dataclass tree (defaults from `base`, except
    those a command gives in `defaults`; help from the field docstring, except `helps`)."""
    known = config_fields(type(base))
    out: dict[str, Setting] = {}
    for name in names:
        if name not in known:
            raise ValueError(f"{type(base).__name__} has no setting {name!r}")
        owner, path, hint = known[name]
        kind, extras = _base_type(hint)
        spec = next((e for e in extras if isinstance(e, CliOption)), None)
        flag = getattr(spec, "flag", None) or "--" + name.replace("_", "-")
        if kind is bool:
            flag = f"{flag}/--no-{flag.removeprefix('--')}"
        value = functools.reduce(getattr, path, base)
        out[name] = Setting(
            owner=owner,
            path=path,
            kind=kind,
            default=defaults.get(name, value),
            help=helps.get(name, field_docs(owner).get(name, "")),
            flag=flag,
            min=getattr(spec, "min", None),
            max=getattr(spec, "max", None),
            own_default=name in defaults,
            own_help=name in helps,
        )
    unknown = (set(defaults) | set(helps)) - set(names)
    if unknown:
        raise ValueError(f"defaults or helps for settings the command does not take: {sorted(unknown)}")
    return out


def _replace_path(cfg: Any, path: tuple[str, ...], value: Any) -> Any:
    if len(path) == 1:
        return replace(cfg, **{path[0]: value})
    return replace(cfg, **{path[0]: _replace_path(getattr(cfg, path[0]), path[1:], value)})


@dataclass(frozen=True)
class Settings:
    """What a command's generated options say: their values by field name, and the config they apply to."""

    base: Any
    specs: Mapping[str, Setting]
    values: Mapping[str, Any]

    def __getitem__(self, name: str) -> Any:
        return self.values[name]

    def config(self) -> Any:
        """The base config with every generated option's value in its field (nested configs too)."""
        cfg = self.base
        for name, value in self.values.items():
            cfg = _replace_path(cfg, self.specs[name].path, value)
        return cfg


def option(setting: Setting) -> Any:
    """The typer annotation of a generated option."""
    text = setting.help.replace("[", "\\[")  # brackets are text, not rich markup
    return Annotated[setting.kind, typer.Option(setting.flag, help=text, min=setting.min, max=setting.max)]


def config_options(
    base: Any,
    names: tuple[str, ...],
    defaults: Mapping[str, Any] | None = None,
    helps: Mapping[str, str] | None = None,
) -> Callable[[F], F]:
    """Decorate a command function: its `settings: Settings` parameter becomes one option per field in
    `names` of the config `base` (in that order, where the parameter stands). `defaults` and `helps`
    are the command's own, named departures from the field's default and docstring. The decorated
    function keeps the generated options in `__settings__` (parameter name -> Setting) and the config
    in `__settings_base__`."""
    specs = settings_of(base, names, defaults or {}, helps or {})

    def decorate(func: F) -> F:
        signature = inspect.signature(func, eval_str=True)
        if SETTINGS_PARAMETER not in signature.parameters:
            raise TypeError(f"{func.__name__} takes no {SETTINGS_PARAMETER!r} parameter")
        clash = set(specs) & set(signature.parameters)
        if clash:
            raise TypeError(f"{func.__name__} declares generated settings itself: {sorted(clash)}")
        params: list[inspect.Parameter] = []
        for p in signature.parameters.values():
            if p.name == SETTINGS_PARAMETER:
                params += [
                    inspect.Parameter(
                        s.name, inspect.Parameter.KEYWORD_ONLY, default=s.default, annotation=option(s)
                    )
                    for s in specs.values()
                ]
            else:
                params.append(p.replace(kind=inspect.Parameter.KEYWORD_ONLY))

        @functools.wraps(func)
        def command(**kwargs: Any) -> Any:
            values = {name: kwargs.pop(name) for name in specs}
            return func(**kwargs, **{SETTINGS_PARAMETER: Settings(base, specs, values)})

        command.__signature__ = signature.replace(parameters=params)  # type: ignore[attr-defined]
        command.__annotations__ = {p.name: p.annotation for p in params}
        command.__settings__ = specs  # type: ignore[attr-defined]
        command.__settings_base__ = base  # type: ignore[attr-defined]
        return command  # type: ignore[return-value]

    return decorate


def generated_settings(callback: Callable[..., Any]) -> Mapping[str, Setting]:
    """The options `config_options` generated for a command function (parameter name -> Setting)."""
    return getattr(callback, "__settings__", {})
