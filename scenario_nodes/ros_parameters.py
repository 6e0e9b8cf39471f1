"""The parameter tables on an rclpy node: declared with their descriptors (description, range,
read-only), integers taken for doubles, read back, and checked against their choices."""

from __future__ import annotations

import weakref
from typing import Sequence

from .parameter_tables import DOUBLE_ARRAY, INTEGER_ARRAY, STRING_ARRAY, Spec, show


def descriptor(spec: Spec):
    """The ParameterDescriptor of ``spec``: its description (with its choices), read-only flag
    and range."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
    text = spec.description
    if spec.choices:
        text += f" (one of: {' | '.join(spec.choices)})"
    result = ParameterDescriptor(name=spec.name, description=text, read_only=spec.read_only)
    if spec.low is not None and not isinstance(spec.default, bool):
        if isinstance(spec.default, int):
            high = int(spec.high) if spec.high is not None else 2 ** 62
            result.integer_range = [IntegerRange(from_value=int(spec.low), to_value=high, step=1)]
        elif isinstance(spec.default, float):
            high = float(spec.high) if spec.high is not None else 1e308
            result.floating_point_range = [
                FloatingPointRange(from_value=float(spec.low), to_value=high, step=0.0)]
    return result


def declare(node, specs: Sequence[Spec], check: bool = True) -> dict:
    """Declare ``specs`` on ``node`` (once; a lifecycle node configured again reads them);
    return name -> value (None for unset arrays). With ``check``, a value outside ``choices``
    raises ValueError naming the parameter (see :func:`check_choices`)."""
    from rclpy.exceptions import ParameterUninitializedException
    from rclpy.parameter import Parameter

    kinds = {DOUBLE_ARRAY: Parameter.Type.DOUBLE_ARRAY, INTEGER_ARRAY: Parameter.Type.INTEGER_ARRAY,
             STRING_ARRAY: Parameter.Type.STRING_ARRAY}
    if node not in _TAKING_INTEGERS:  # runtime sets too (`ros2 param set ... 10`), once per node
        node.add_pre_set_parameters_callback(lambda parameters: integers_as_doubles(node, parameters))
        _TAKING_INTEGERS.add(node)
    values = {}
    for spec in specs:
        if node.has_parameter(spec.name):  # a lifecycle node configured again
            values[spec.name] = node.get_parameter(spec.name).value
        elif spec.default is None:
            node.declare_parameter(spec.name, kinds[spec.kind], descriptor(spec))
            try:
                values[spec.name] = node.get_parameter(spec.name).value
            except ParameterUninitializedException:
                values[spec.name] = None
        else:
            values[spec.name] = _declare_with_coercion(node, spec)
    if check:
        check_choices(values, specs)
    return values


#: Nodes whose parameter services already take an integer for a double (see declare).
_TAKING_INTEGERS: weakref.WeakSet = weakref.WeakSet()


def integers_as_doubles(node, parameters: list) -> list:
    """A pre-set-parameters callback: an integer (or a list of integers) set for a declared
    double parameter becomes that double. ``ros2 param set /cw_plant real_time_factor 10``
    sends an INTEGER ParameterValue, which rclpy would refuse as the wrong type; every other
    parameter passes unchanged (rclpy and the node's own callback then check it as usual)."""
    from rclpy.parameter import Parameter
    kind = Parameter.Type
    widened = {kind.INTEGER: kind.DOUBLE, kind.INTEGER_ARRAY: kind.DOUBLE_ARRAY}
    out = []
    for parameter in parameters:
        target = widened.get(parameter.type_)
        if target is not None and node.has_parameter(parameter.name):
            described = node.describe_parameter(parameter.name)
            if not described.dynamic_typing and described.type == target.value:
                value = (float(parameter.value) if target == kind.DOUBLE
                         else [float(v) for v in parameter.value])
                parameter = Parameter(parameter.name, target, value)
        out.append(parameter)
    return out


def _is_double(default) -> bool:
    return (isinstance(default, float)
            or (isinstance(default, list) and bool(default) and all(isinstance(v, float) for v in default)))


def coerce(spec: Spec, value):
    """``value`` as the type of ``spec``'s default where that is exact: an integer (or a list
    of integers) given for a double (``-p real_time_factor:=10``) becomes a double; anything
    else is returned as it is."""
    if isinstance(spec.default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if (_is_double(spec.default) and isinstance(value, (list, tuple)) and value
            and all(isinstance(v, int) and not isinstance(v, bool) for v in value)):
        return [float(v) for v in value]
    return value


def _declare_with_coercion(node, spec: Spec):
    """Declare ``spec`` with its value from the overrides, an integer given for a double
    accepted as that double; a value of another type refused naming the parameter and the fix."""
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.exceptions import InvalidParameterTypeException
    if not _is_double(spec.default):
        return _declare_static(node, spec, spec.default, ignore_override=False)
    # read the override as given (any type), then declare the parameter with its type
    probe = ParameterDescriptor(name=spec.name, dynamic_typing=True)
    given = node.declare_parameter(spec.name, spec.default, probe).value
    node.undeclare_parameter(spec.name)
    value = coerce(spec, given)
    scalar = isinstance(spec.default, float)
    if not (isinstance(value, float) if scalar else
            not isinstance(value, (str, bytes)) and all(isinstance(v, float) for v in value)):
        kind = 'double' if scalar else 'list of doubles'
        raise ValueError(f'parameter {spec.name} must be a {kind} (e.g. {spec.name}:={show(spec.default)}); '
                         f'got {given!r}')
    try:
        return node.declare_parameter(spec.name, value, descriptor(spec), ignore_override=True).value
    except InvalidParameterTypeException as error:  # not expected after the check: say it anyway
        raise ValueError(f'parameter {spec.name}: {error}') from None


def _declare_static(node, spec: Spec, default, ignore_override: bool):
    from rclpy.exceptions import InvalidParameterTypeException
    try:
        return node.declare_parameter(spec.name, default, descriptor(spec), ignore_override=ignore_override).value
    except InvalidParameterTypeException as error:
        raise ValueError(f'parameter {spec.name} must be of the type of its default '
                         f'{show(spec.default)} ({error})') from None


def read(node, specs: Sequence[Spec]) -> dict:
    """The current values of declared ``specs`` (None for an array never set)."""
    from rclpy.exceptions import ParameterUninitializedException
    values = {}
    for spec in specs:
        try:
            values[spec.name] = node.get_parameter(spec.name).value
        except ParameterUninitializedException:
            values[spec.name] = None
    return values


def check_choices(values: dict, specs: Sequence[Spec]) -> None:
    """ValueError naming the first parameter whose value is not one of its choices."""
    for spec in specs:
        if spec.choices and values.get(spec.name) not in spec.choices:
            raise ValueError(f"parameter {spec.name} must be one of {' | '.join(spec.choices)}; "
                             f'got {values.get(spec.name)!r}')
