"""The small learned models run in numpy: no node imports torch unless its detector is CuTR.

Torch costs a node process about 180 MB of resident memory; the learned object matcher and
the box refiner are a few dense layers each, which numpy runs as fast. Training
(:mod:`rfm_core.training`) uses torch and writes the weights as an ``.npz`` archive: one
array per parameter, named as in the training module's ``state_dict``, plus ``__meta__``
(JSON: the file's format and version and the training metadata). :func:`load_weights`
checks the names, shapes and values before a network is built from them.
"""
from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np
from scipy.special import erf

__all__ = ['save_weights', 'load_weights', 'linear', 'layer_norm', 'gelu', 'relu', 'log_softmax', 'log_sigmoid',
           'attention']

_META = '__meta__'


def save_weights(path, arrays: dict, meta: dict) -> None:
    """Write ``arrays`` ({name: array}) and ``meta`` (JSON-able; must hold 'format' and
    'version') to ``path`` atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + '.tmp.npz')
    np.savez_compressed(tmp, **{k: np.asarray(v) for k, v in arrays.items()},
                        **{_META: np.frombuffer(json.dumps(meta).encode(), np.uint8)})
    os.replace(tmp, path)


def load_weights(path, fmt: str, version: int, shapes: dict | None = None, train_command: str = '') -> tuple:
    """(float32 arrays, meta) of a weights file of format ``fmt`` and ``version``.

    ``shapes`` ({name: shape}, or a function of the meta giving it) is what the network needs:
    every array must be there, no other, each of that shape and finite. FileNotFoundError for
    a missing file, ValueError saying what is wrong and what to do (``train_command``) for
    anything else.
    """
    path = Path(path)
    retrain = f'; retrain it with `{train_command}`' if train_command else ''
    if not path.is_file():
        raise FileNotFoundError(f'weights not found: {path} (train them with `{train_command}`)')
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {k: archive[k] for k in archive.files}
        meta = json.loads(arrays.pop(_META).tobytes().decode())
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, UnicodeDecodeError, EOFError) as exc:
        raise ValueError(f'{path} cannot be read as {fmt} weights ({exc.__class__.__name__}: {exc}){retrain}') from exc
    if not isinstance(meta, dict) or meta.get('format') != fmt:
        raise ValueError(f'{path} is not an {fmt} weights file{retrain}')
    if meta.get('version') != version:
        raise ValueError(f'{path}: unsupported {fmt} weights version {meta.get("version")!r}{retrain}')
    if callable(shapes):
        try:
            shapes = shapes(meta)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f'{path}: its description is incomplete ({exc}){retrain}') from exc
    if shapes is not None:
        if set(arrays) != set(shapes):
            missing, extra = sorted(set(shapes) - set(arrays)), sorted(set(arrays) - set(shapes))
            raise ValueError(f'{path}: parameters do not fit the network (missing {missing[:3]}, '
                             f'unexpected {extra[:3]}){retrain}')
        for name, shape in shapes.items():
            if arrays[name].shape != tuple(shape):
                raise ValueError(f'{path}: {name} has shape {arrays[name].shape}, expected {tuple(shape)}{retrain}')
    out = {}
    for name, a in arrays.items():
        if a.dtype.kind != 'f' or not np.all(np.isfinite(a)):
            raise ValueError(f'{path}: {name} is not finite floating point{retrain}')
        out[name] = a.astype(np.float32)
    return out, meta


def linear(x: np.ndarray, params: dict, name: str) -> np.ndarray:
    """torch.nn.Linear (or a kernel-1 Conv1d over the last axis) named ``name`` in ``params``."""
    w = params[f'{name}.weight']
    out = x.reshape(-1, x.shape[-1]) @ w.reshape(w.shape[0], -1).T      # one BLAS call over all tokens
    return (out + params[f'{name}.bias']).reshape(*x.shape[:-1], w.shape[0])


def layer_norm(x: np.ndarray, params: dict, name: str, eps: float = 1e-5) -> np.ndarray:
    mean = x.mean(-1, keepdims=True)
    var = ((x - mean) ** 2).mean(-1, keepdims=True)
    return (x - mean) / np.sqrt(var + eps) * params[f'{name}.weight'] + params[f'{name}.bias']


def gelu(x: np.ndarray) -> np.ndarray:
    """torch.nn.GELU (the exact one)."""
    return (0.5 * x * (1.0 + erf(x / np.sqrt(2.0)))).astype(x.dtype)


def relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0)


def log_softmax(x: np.ndarray, axis: int) -> np.ndarray:
    shifted = x - x.max(axis, keepdims=True)
    return shifted - np.log(np.exp(shifted).sum(axis, keepdims=True))


def log_sigmoid(x: np.ndarray) -> np.ndarray:
    return -np.logaddexp(0, -x).astype(x.dtype)


def attention(q: np.ndarray, k: np.ndarray, v: np.ndarray, key_mask: np.ndarray, heads: int) -> np.ndarray:
    """Multi-head scaled dot-product attention of (B, N, D) queries over (B, M, D) keys and
    values; ``key_mask`` (B, M): True for a real key (each row needs one)."""
    b, n, d = q.shape
    q, k, v = (t.reshape(b, -1, heads, d // heads).transpose(0, 2, 1, 3) for t in (q, k, v))
    logits = q @ k.transpose(0, 1, 3, 2) / np.float32(np.sqrt(d // heads))
    logits = np.where(key_mask[:, None, None, :], logits, -np.inf)
    logits -= logits.max(-1, keepdims=True)
    p = np.exp(logits)
    p /= p.sum(-1, keepdims=True)
    return (p @ v).transpose(0, 2, 1, 3).reshape(b, n, d)
