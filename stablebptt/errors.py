"""The exceptions that mean: say so in one line, no traceback.

Library errors name what a Python user set: a config field (``TrainConfig.lr``,
``mjcf.Config.dt``), a ``Dynamics`` or a ``Plan`` field. The command line shows
each as its option (``--lr``, ``--dt``): ``as_options``.
"""
import dataclasses
import difflib
import functools
import inspect
import numbers
import re
import sys

# A field the command line sets under another name.
_OPTION_OF = {"Dynamics.horizon": "steps"}
_FIELD = re.compile(r"\b(?:[a-z_]\w*\.)?((?:\w*Config|Dynamics|Plan)\.([a-z_]\w*))")  # (owner.field, field)


def config_field(config, name: str) -> str:
    """How errors name field ``name`` of a config (class or instance): ``TrainConfig.lr``, ``mjcf.Config.dt``."""
    cls = config if isinstance(config, type) else type(config)
    owner = cls.__name__ if cls.__name__ != "Config" else f"{cls.__module__.rsplit('.', 1)[-1]}.Config"
    return f"{owner}.{name}"


def first_line(error: Exception) -> str:
    """An error in one line: its type and the first line of its message."""
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0] if text else ''}"


def whole_number(value) -> bool:
    """An int or NumPy integer, not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def real_number(value) -> bool:
    """An int, float or NumPy number that is not a bool (NaN and infinities included)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _numpy_bool(value) -> bool:
    return type(value).__module__ == "numpy" and type(value).__name__ in ("bool", "bool_")  # NumPy 2's and 1's


def plain_scalar(value):
    """A config field's number or truth value of a kind JSON cannot write (a NumPy scalar, a Fraction) as
    Python's own; a NumPy float as the shortest decimal that reads back to it, the number its user wrote
    (``np.float32(1e-3)``: 0.001, not 0.0010000000474974513). TypeError for anything else."""
    if _numpy_bool(value):
        return bool(value)
    if whole_number(value):
        return int(value)
    if real_number(value):
        return float(str(value)) if type(value).__module__ == "numpy" else float(value)
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


# What a config field annotated int, float, str or bool takes (a NumPy scalar too).
_KINDS = {"int": whole_number,
          "float": real_number,
          "str": lambda value: isinstance(value, str),
          "bool": lambda value: isinstance(value, bool) or _numpy_bool(value)}


def field_kind(item: dataclasses.Field) -> str | None:
    """The name of config field ``item``'s annotated type; a union (``int | None``) is no kind of ``_KINDS``."""
    return item.type if isinstance(item.type, str) else getattr(item.type, "__name__", None)


def wrong_kind(item: dataclasses.Field, value, named: str) -> str | None:
    """The refusal of ``value`` for config field ``item`` (as ``named``) where it is not of the field's kind."""
    kind = field_kind(item)
    if kind in _KINDS and not _KINDS[kind](value):
        return f"{named} must be {'a whole number' if kind == 'int' else kind}, got {value!r}"
    return None


def check_field_types(config) -> None:
    """``InputError`` naming the first field of the dataclass ``config`` whose value is not of its annotated
    kind: from Python anything can arrive (2.5 epochs, lr "0.1", batch None, poles "2")."""
    for item in dataclasses.fields(config):
        value = getattr(config, item.name)
        if refusal := wrong_kind(item, value, config_field(config, item.name)):
            raise InputError(refusal)
        if field_kind(item) == "float" and isinstance(value, numbers.Integral) and abs(value) > sys.float_info.max:
            raise InputError(f"{config_field(config, item.name)} is past the largest float, got an integer of "
                             f"{int(value).bit_length()} bits")  # its digits may be too many for str()


def as_options(message: str) -> str:
    """``message`` with every config or Plan field, and the Dynamics fields the command line sets, named as
    its command-line option. ``Dynamics.step``, ``.policy`` and ``.loss`` are a task's code, no option:
    they keep their names."""
    def option(match: re.Match) -> str:
        if match.group(1).startswith("Dynamics.") and match.group(1) not in _OPTION_OF:
            return match.group(1)
        return "--" + _OPTION_OF.get(match.group(1), match.group(2)).replace("_", "-")
    return _FIELD.sub(option, message)


class InputError(ValueError):
    """Bad user input. Scripts print its message as one line and exit with code 2."""


def refuse_keyword(keyword: str, taken, named, refusal: str) -> None:
    """``InputError``: ``refusal`` of ``keyword`` and the nearest of the keywords ``taken``, as ``named`` names one."""
    nearest = difflib.get_close_matches(keyword, taken, n=1)
    raise InputError(refusal + (f": did you mean {named(nearest[0])}?" if nearest else ""))


def keywords_named(target):
    """``target``, a config dataclass or a public function, refusing a keyword it does not take with an
    ``InputError`` that names the nearest one it takes (Python's own refusal is a TypeError): from Python a
    misspelt option (``TrainConfig(critc=True)``) is bad input, as on the command line."""
    config = isinstance(target, type)
    function = target.__init__ if config else target
    parameters = inspect.signature(function).parameters.values()
    if any(parameter.kind == parameter.VAR_KEYWORD for parameter in parameters):
        raise TypeError(f"{target.__qualname__} takes any keyword (**): it refuses its own")  # Dynamics does
    taken = frozenset(parameter.name for parameter in parameters if parameter.name != "self"
                      and parameter.kind in (parameter.POSITIONAL_OR_KEYWORD, parameter.KEYWORD_ONLY))

    @functools.wraps(function)
    def checked(*args, **keywords):
        for keyword in keywords:  # the first unknown in the caller's order
            if keyword in taken:
                continue
            if config:  # named after the instance's class: a subclass that is no dataclass of its own inherits this
                named = functools.partial(config_field, type(args[0]) if args else target)
                refuse_keyword(keyword, taken, named, f"no field {named(keyword)}")
            refuse_keyword(keyword, taken, repr, f"{target.__name__}() takes no argument {keyword!r}")
        return function(*args, **keywords)

    if config:
        target.__init__ = checked
        return target
    return checked


class TaskError(InputError):
    """A ``Task`` or its ``Dynamics`` that cannot train: the message names the field."""


def users_call(failing: str, call):
    """``call()``; where a user's function fails in it, a ``TaskError`` of one line, ``failing`` and the error's
    first line. The library's own refusal (an env's, inside a task's function) passes in its words."""
    try:
        return call()
    except InputError:
        raise
    except Exception as error:  # noqa: BLE001 - the user's function failed: one line naming it
        raise TaskError(f"{failing}: {first_line(error)}") from None


class StorageError(OSError):
    """A file could not be written (full disk, permissions). Scripts print one line and exit with code 1."""
