"""Fill any ROS message with deterministic, non-trivial values (from its rosidl type info).

Used by both processes of the interface round-trip test, so every field of every rfm_msgs
type is exercised, including fields added later.
"""
import hashlib
import importlib
import random

from rosidl_parser.definition import (
    AbstractSequence, AbstractString, AbstractWString, Array, BasicType, NamespacedType,
)

_INT_RANGES = {
    'int8': (-128, 127), 'uint8': (0, 255), 'int16': (-32768, 32767), 'uint16': (0, 65535),
    'int32': (-2**31, 2**31 - 1), 'uint32': (0, 2**32 - 1),
    'int64': (-2**63, 2**63 - 1), 'uint64': (0, 2**64 - 1),
}


def _basic(typename, rng):
    if typename in _INT_RANGES:
        lo, hi = _INT_RANGES[typename]
        return rng.choice([lo, hi, rng.randint(lo, hi)])
    if typename in ('float', 'double'):
        return rng.randint(-100000, 100000) / 64.0    # exact in float32
    if typename == 'boolean':
        return rng.random() < 0.5
    if typename == 'octet':
        return bytes([rng.randint(0, 255)])
    if typename == 'char':
        return chr(rng.randint(33, 126))
    raise TypeError(f'unhandled basic type {typename}')


def message_class(namespaced):
    module = importlib.import_module('.'.join(namespaced.namespaces))
    return getattr(module, namespaced.name)


def _value(slot, rng, depth):
    if isinstance(slot, BasicType):
        return _basic(slot.typename, rng)
    if isinstance(slot, (AbstractString, AbstractWString)):
        return 'rfm-' + ''.join(rng.choice('abcxyz_0123 ÄØ') for _ in range(rng.randint(1, 12)))
    if isinstance(slot, NamespacedType):
        return fill(message_class(slot)(), rng, depth + 1)
    if isinstance(slot, Array):
        return [_value(slot.value_type, rng, depth) for _ in range(slot.size)]
    if isinstance(slot, AbstractSequence):
        n = rng.randint(1, 3) if depth < 4 else 0
        return [_value(slot.value_type, rng, depth) for _ in range(n)]
    raise TypeError(f'unhandled slot type {slot!r}')


def fill(msg, rng: random.Random, depth: int = 0):
    """Set every field of ``msg`` to a random value drawn from ``rng``; returns ``msg``."""
    for (name, _), slot in zip(msg.get_fields_and_field_types().items(), msg.SLOT_TYPES):
        setattr(msg, name, _value(slot, rng, depth))
    return msg


def interface_types():
    """(messages, services): every interface of rfm_msgs plus tf2_msgs/TFMessage."""
    import rfm_msgs.msg
    import rfm_msgs.srv
    from tf2_msgs.msg import TFMessage

    msgs = [getattr(rfm_msgs.msg, n) for n in sorted(dir(rfm_msgs.msg))
            if isinstance(getattr(rfm_msgs.msg, n), type)
            and hasattr(getattr(rfm_msgs.msg, n), 'get_fields_and_field_types')]
    srvs = [getattr(rfm_msgs.srv, n) for n in sorted(dir(rfm_msgs.srv))
            if isinstance(getattr(rfm_msgs.srv, n), type)
            and hasattr(getattr(rfm_msgs.srv, n), 'Request')]
    return msgs + [TFMessage], srvs


def response_for(srv_type, request):
    """The response the echo server returns: seeded by the request's contents.

    (Not by its CDR bytes: alignment padding in them is uninitialised memory.)
    """
    seed = int.from_bytes(hashlib.sha256(repr(request).encode()).digest()[:8], 'little')
    return fill(srv_type.Response(), random.Random(seed))
