"""Command-line checks that run before Hydra starts a job.

``python -m cdqn.train`` and ``python -m cdqn.evaluate`` call :func:`preflight` on their
arguments first.  It composes the configuration exactly as Hydra will (for a multirun:
every swept value once), applies the schema's validation and reports every problem in one
message that names the key, the value and what is allowed, then exits with status 2::

    cdqn: invalid configuration, nothing was started:
      - controller=foo: unknown controller; allowed: ddqn, h2, hinf, hinf_f, none
      - network.width=abc: Value 'abc' of type 'str' could not be converted to Integer
        (network.width takes int)

``--config-dir``/``--config-name`` (the sweeps in ``sweeps/``) are checked the same way,
the sweep config's own ``hydra.sweeper.params`` included.  Flags that change what Hydra
does (``--cfg``, ``--help``, ...) skip the check and leave everything to Hydra.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import re
import sys
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override, ValueType
from hydra.errors import HydraException, MissingConfigException, OverrideParseException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import (
    ConfigAttributeError,
    ConfigKeyError,
    MissingMandatoryValue,
    OmegaConfBaseException,
    ValidationError,
)

from cdqn.config import (
    CONF_DIR,
    Config,
    ConfigError,
    EnvConfig,
    EvaluateConfig,
    register_configs,
    to_schema,
    validate_evaluate,
)

EXIT_CONFIG = 2
"""Exit status of a command refused for its configuration."""
MAX_COMPOSITIONS = 64
"""A multirun is checked with at most this many compositions (each swept value once)."""


_HYDRA_ONLY_FLAGS = {
    "-h", "--help", "--hydra-help", "-i", "--info", "--version", "-c", "--cfg", "--resolve",
    "-p", "--package", "-sc", "--shell-completion", "-cp", "--config-path", "-cn",
    "--config-name", "-cd", "--config-dir", "--experimental-rerun",
}  # fmt: skip
_RESUME_ALLOWED = re.compile(r"^(resume|tracking|tracking\.\w+|train\.progress|hydra[./].*)$")

register_configs()


def run_command(main: Callable[[list[str]], object]) -> None:
    """Run an argparse command (``python -m cdqn.bench``, ``python -m cdqn.profile``) on the
    process's arguments; a refused configuration is one line ``error: ...`` on stderr and
    exit status :data:`EXIT_CONFIG`."""
    try:
        main(sys.argv[1:])
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(EXIT_CONFIG)


def start_hydra(
    main: Callable[[], object],
    config_name: str = "config",
    check: Callable[[DictConfig], None] | None = None,
) -> None:
    """Start a Hydra command (``python -m cdqn.train``, ``cdqn.evaluate``, ``cdqn.tune``):
    MLflow's artifact progress bars off, :func:`preflight` on the process's arguments
    with ``check`` (default :func:`check_train`), then ``main``."""
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    preflight(sys.argv[1:], config_name, check or check_train)
    main()


def check_train(cfg: DictConfig) -> None:
    """What ``python -m cdqn.train`` refuses: the environment's adoption, the schema's
    rules (:func:`cdqn.envs.adopt`), and the environment as the run would build it."""
    if cfg.get("resume"):
        return  # the stored configuration is checked when the run is resumed
    from cdqn.envs import adopt

    _check_env(_env_key(adopt(cfg).conf.env))


def _env_key(env: EnvConfig) -> str:
    """``env`` as a hashable key of :func:`_check_env`."""
    return json.dumps(dataclasses.asdict(env), sort_keys=True)


@functools.lru_cache(maxsize=32)
def _check_env(key: str) -> None:
    """Build the environment once as the run would (id, kwargs, cap, features, scale,
    radial features); a multirun checks each distinct environment once."""
    from cdqn.envs import make_env

    make_env(EnvConfig(**json.loads(key))).close()


def check_evaluate(cfg: DictConfig) -> None:
    """What ``python -m cdqn.evaluate`` refuses."""
    validate_evaluate(to_schema(cfg, EvaluateConfig))


def preflight(
    argv: list[str],
    config_name: str = "config",
    check: Callable[[DictConfig], None] = check_train,
) -> None:
    """Exit with status 2 and a clear message when ``argv`` cannot run (module docstring)."""
    source = _config_source(argv)
    if source is None:
        return
    argv, config_dir, name = source
    if any(a.split("=", 1)[0] in _HYDRA_ONLY_FLAGS for a in argv):
        return
    multirun = any(a in ("-m", "--multirun") for a in argv)
    overrides = [a for a in argv if not a.startswith("-")]
    try:
        errors = check_overrides(overrides, multirun, name or config_name, check, config_dir)
    except (HydraException, OmegaConfBaseException) as err:  # e.g. no such --config-name
        errors = [explain(err)]
    if errors:
        lines = "\n".join(f"  - {e}" for e in errors)
        print(f"cdqn: invalid configuration, nothing was started:\n{lines}", file=sys.stderr)
        sys.exit(EXIT_CONFIG)


def _config_source(argv: list[str]) -> tuple[list[str], Path | None, str | None] | None:
    """``argv`` without ``--config-dir``/``--config-name`` (and short forms) and their
    values; None when a value is missing."""
    rest: list[str] = []
    found: dict[str, str] = {}
    names = {"-cd": "dir", "--config-dir": "dir", "-cn": "name", "--config-name": "name"}
    i = 0
    while i < len(argv):
        flag, eq, value = argv[i].partition("=")
        if flag in names:
            if not eq:
                if i + 1 >= len(argv):
                    return None
                value, i = argv[i + 1], i + 1
            found[names[flag]] = value
        else:
            rest.append(argv[i])
        i += 1
    config_dir = Path(found["dir"]).resolve() if "dir" in found else None
    return rest, config_dir, found.get("name")


def _sweeper_params(config_dir: Path, config_name: str, searchpath: list[str]) -> list[str]:
    """The ``hydra.sweeper.params`` of a sweep config as overrides (``key=a,b,c``)."""
    with initialize_config_dir(str(config_dir), version_base="1.3"):
        cfg = compose(config_name, overrides=searchpath, return_hydra_config=True)
    params = OmegaConf.select(cfg, "hydra.sweeper.params") or {}
    return [f"{k}={v}" for k, v in params.items()]


def check_overrides(
    overrides: list[str],
    multirun: bool = False,
    config_name: str = "config",
    check: Callable[[DictConfig], None] = check_train,
    config_dir: Path | None = None,
) -> list[str]:
    """The problems of a command line, one message each (empty: it can run).

    ``config_dir`` (``--config-dir``, e.g. ``sweeps``): the primary config comes from there,
    with ``conf/`` on the search path, and in a multirun the config's own
    ``hydra.sweeper.params`` are swept too (the command line's value of a key wins)."""
    parsed = _parsed(overrides)
    if isinstance(parsed, str):
        return [parsed]
    dirs = preset_dirs(parsed, config_name)
    searchpath: list[str] = []
    if config_dir is not None and config_dir != CONF_DIR:
        # conf/ and the user's folders on one search path (a later hydra.searchpath replaces)
        entries = ",".join(f"file://{d}" for d in [CONF_DIR, *dirs])
        searchpath = [f"hydra.searchpath=[{entries}]"]
        overrides = [o for o in overrides if not o.startswith("hydra.searchpath=")]
        if multirun:
            given = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
            firsts = [f"{ov.key_or_group}={v[0]}" for ov in parsed if not ov.is_hydra_override()
                      and not ov.is_add() and (v := _values(ov))]  # fmt: skip
            params = _sweeper_params(config_dir, config_name, [*searchpath, *firsts])
            overrides = [p for p in params if p.split("=", 1)[0] not in given] + overrides
        parsed = _parsed(overrides)
        assert not isinstance(parsed, str)
    errors = _group_errors(parsed, dirs)
    if config_name == "config" and any(o.key_or_group == "resume" for o in parsed):
        if any(o.key_or_group == "resume" and not str(o.value() or "").strip() for o in parsed):
            errors.append(
                "resume='': give the MLflow run id of the run to continue, resume=<run_id>"
            )
        errors += resume_conflicts(overrides)
    if errors:
        return errors
    jobs = _jobs(parsed, overrides, multirun)
    if jobs is None:
        return []  # sweeps Hydra expands itself (glob, interval): Hydra checks them
    with initialize_config_dir(str(config_dir or CONF_DIR), version_base="1.3"):
        for job in jobs[:MAX_COMPOSITIONS]:
            for msg in _check_one([*searchpath, *job], config_name, check):
                if msg not in errors:
                    errors.append(msg)
    return errors


def _parsed(overrides: list[str]) -> list[Override] | str:
    """The parsed overrides, or the one-line message of the first that does not parse."""
    parser = OverridesParser.create()
    parsed: list[Override] = []
    for text in overrides:
        try:
            parsed.extend(parser.parse_overrides([text]))
        except OverrideParseException as err:
            first = str(err).splitlines()[0]
            return f"{text}: cannot parse ({first}); see Hydra's override grammar"
    return parsed


def resume_conflicts(overrides: list[str]) -> list[str]:
    """Overrides that make no sense with ``resume=<run_id>`` (it continues the stored config)."""
    bad = [o for o in overrides if not _RESUME_ALLOWED.match(o.split("=", 1)[0].lstrip("+~"))]
    if not bad:
        return []
    return [
        f"{' '.join(bad)}: resume=<run_id> continues the run with its stored configuration; "
        "allowed alongside it: tracking.*, train.progress (start a new run to change anything "
        "else)"
    ]


def _group_errors(parsed: list[Override], presets: list[Path]) -> list[str]:
    groups = {d.name for d in CONF_DIR.iterdir() if d.is_dir()}
    errors = []
    for ov in parsed:
        group = ov.key_or_group
        if group not in groups or ov.is_delete() or ov.package is not None:
            continue
        options = sorted({p.stem for d in (CONF_DIR, *presets) for p in (d / group).glob("*.yaml")})
        for value in _values(ov) or []:
            if value not in options:
                errors.append(f"{group}={value}: unknown {group}; allowed: {', '.join(options)}")
    return errors


def preset_dirs(parsed: list[Override], config_name: str = "config") -> list[Path]:
    """User config folders on Hydra's search path: the ``file://`` entries of a
    ``hydra.searchpath=[...]`` override (``python -m cdqn.train weights=<preset>
    hydra.searchpath=[file://presets]``); ``python -m cdqn.tune`` has
    ``$CDQN_PRESETS`` (else ``presets``) on it by default (conf/tune.yaml)."""
    dirs = []
    for ov in parsed:
        if ov.get_key_element() == "hydra.searchpath":
            value = ov.value()
            entries = value if isinstance(value, list) else [value]
            dirs += [
                Path(str(e)[len("file://") :]) for e in entries if str(e).startswith("file://")
            ]
    if config_name == "tune" and not dirs:
        dirs.append(Path(os.environ.get("CDQN_PRESETS", "presets")))
    return dirs


def _values(ov: Override) -> list[str] | None:
    """The values of an override (several for a sweep), None when Hydra must expand them."""
    if not ov.is_sweep_override():
        return [ov.get_value_element_as_str()]
    if ov.value_type == ValueType.GLOB_CHOICE_SWEEP or not ov.is_discrete_sweep():
        return None
    return list(ov.sweep_string_iterator())


def _jobs(parsed: list[Override], texts: list[str], multirun: bool) -> list[list[str]] | None:
    """Override lists to compose: the first value of every sweep, then each other value once."""
    base: list[str] = []
    variants: list[tuple[int, list[str]]] = []
    for ov, text in zip(parsed, texts, strict=True):
        if ov.is_hydra_override() and ov.get_key_element() != "hydra.searchpath":
            continue
        if not (multirun and ov.is_sweep_override()):
            base.append(text)
            continue
        values = _values(ov)
        if not values:
            return None
        key = ov.get_key_element()
        base.append(f"{key}={values[0]}")
        variants.append((len(base) - 1, [f"{key}={v}" for v in values[1:]]))
    jobs = [base]
    for i, alternatives in variants:
        jobs += [[*base[:i], alt, *base[i + 1 :]] for alt in alternatives]
    return jobs


def _check_one(
    overrides: list[str], config_name: str, check: Callable[[DictConfig], None]
) -> list[str]:
    schema = EvaluateConfig if config_name == "evaluate" else Config
    from cdqn.envs.adopt import command_line

    try:
        with command_line(overrides):
            check(compose(config_name, overrides=overrides))
    except ConfigError as err:
        items = [ln.strip()[2:] for ln in str(err).splitlines() if ln.strip().startswith("- ")]
        return items or [str(err)]
    except (HydraException, OmegaConfBaseException) as err:
        return [explain(err, schema)]
    return []


def explain(err: Exception, schema: type = Config) -> str:
    """One line for a Hydra/OmegaConf composition error: key, value and what is allowed."""
    cause = err.__cause__ if isinstance(err.__cause__, OmegaConfBaseException) else err
    full_key = getattr(cause, "full_key", None) or ""
    key = re.sub(r"\[\d+\]$", "", full_key)
    merging = re.search(r"Error merging override (\S+)", str(err))
    if isinstance(cause, ConfigAttributeError | ConfigKeyError) and full_key:
        parent, _, _ = key.rpartition(".")
        if typing.get_origin(_walk(schema, parent)) is dict:  # a mapping, e.g. env.kwargs
            return f"{key}: {parent} has no such key yet; add it with +{key}=<value>"
        names = _field_names(schema, parent)
        where = f" in {parent}" if parent else ""
        return f"{key}: no such setting{where}; allowed: {', '.join(names)}"
    if isinstance(cause, ValidationError) and full_key:
        text = merging[1] if merging else f"{key}={cause.value!r}"
        expected = _field_type(schema, key)
        msg = (cause.msg or str(cause)).splitlines()[0]
        return f"{text}: {msg}" + (f" ({key} takes {expected})" if expected else "")
    if isinstance(cause, MissingMandatoryValue) and full_key:
        return f"{key}: required, give {key}=<value>"
    if isinstance(err, MissingConfigException):
        return " ".join(str(err).split("Config search path")[0].split())
    return " ".join(str(err).split("Config search path")[0].split())


def _walk(schema: type, dotted: str) -> type | None:
    cls: Any = schema
    for part in [p for p in dotted.split(".") if p]:
        if not dataclasses.is_dataclass(cls):
            return None
        cls = typing.get_type_hints(cls).get(part)
    return cls


def _field_names(schema: type, parent: str) -> list[str]:
    cls = _walk(schema, parent)
    return [f.name for f in dataclasses.fields(cls)] if dataclasses.is_dataclass(cls) else []


def _field_type(schema: type, key: str) -> str | None:
    parent, _, leaf = key.rpartition(".")
    cls = _walk(schema, parent)
    if not dataclasses.is_dataclass(cls):
        return None
    for f in dataclasses.fields(cls):
        if f.name == leaf:
            return f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    return None
