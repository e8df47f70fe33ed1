"""ROS parameters from rfm's configuration dataclasses (:mod:`rfm_core.config`).

A node calls :func:`declare_config` once per configuration it runs with: every setting
becomes a typed parameter with its description, range and read-only flag, named as
:func:`rfm_core.settings.settings_of` lists it (``keyframes.min_overlap``), and the
configuration comes back with the values the node was started with. rclpy is only used
through the node passed in, so this module imports without ROS.
"""
from __future__ import annotations

from rfm_core.io.messages import ROS
from rfm_core.settings import Setting, settings_of, with_values

__all__ = ['parameter_descriptor', 'declare_config']


def parameter_descriptor(text: str, lo=None, hi=None, integer: bool = False, read_only: bool = False,
                         make=ROS):
    """rcl_interfaces/ParameterDescriptor: a description and optionally a range."""
    fields = {'description': text, 'read_only': read_only}
    if lo is not None and hi is not None and integer:
        fields['integer_range'] = [make('rcl_interfaces/msg/IntegerRange', from_value=int(lo), to_value=int(hi),
                                        step=1)]
    elif lo is not None and hi is not None:
        fields['floating_point_range'] = [make('rcl_interfaces/msg/FloatingPointRange', from_value=float(lo),
                                               to_value=float(hi), step=0.0)]
    return make('rcl_interfaces/msg/ParameterDescriptor', **fields)


def _descriptor(s: Setting, make=ROS):
    text = s.description
    if s.choices:
        text += ' (one of: ' + ', '.join(repr(c) for c in s.choices) + ')'
    if s.paper is not None:
        text += f' (paper: {s.paper})'
    return parameter_descriptor(text, s.lo, s.hi, integer=s.kind == 'int', read_only=s.read_only, make=make)


def declare_config(node, config):
    """Declare every setting of ``config`` as a parameter of ``node`` and return ``config``
    with the node's values (its overrides, launch files, parameter files). ValueError naming
    the parameter when a value has the wrong type or is out of range."""
    values = {}
    for s in settings_of(config):
        try:
            value = node.declare_parameter(s.name, s.default, _descriptor(s)).value
        except Exception as exc:     # rclpy's InvalidParameterTypeException / ...ValueException
            raise ValueError(f'parameter {s.name} ({s.kind}, default {s.default!r}): {exc}') from None
        values[s.name] = list(value) if s.kind == 'float[]' else value
    return with_values(config, values)
