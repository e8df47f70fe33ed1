"""Class names: NYU40's, as ScanNet uses them, and a user's renames (``label_map``).

Every detection leaves the detector with a name from :data:`NYU40` (Silberman et al., 2012;
Gupta et al., 2013: the 40 classes of NYU Depth v2, ScanNet's ``nyu40class`` column), so a
map's objects read and score like those of the datasets people compare on. The detectors'
own classes (:data:`rfm_core.detection.box_refiner.CLASSES`, the simulator's kinds) are
named by :data:`TO_NYU40`; a kind NYU40 has no class of its own goes to the class whose
definition holds it (our reading: ``armchair`` and ``stool`` are chairs, ``monitor`` and
``tv`` television, ``wardrobe`` a cabinet, ``tv_stand`` other furniture, ``bin``, ``plant``,
``vase`` and ``bowl`` other props).

``label_map`` entries ``FROM:TO`` (comma-separated in the parameter) rename or merge on top
of that: ``FROM`` is a detector class (``monitor:monitor`` keeps monitors apart from
televisions) or an NYU40 name (``otherprop:clutter`` renames every class NYU40 calls a
prop); ``TO`` is any name.
"""
from __future__ import annotations

from functools import lru_cache

__all__ = ['NYU40', 'TO_NYU40', 'LabelMap', 'parse_label_map', 'label_map']

#: NYU40's class names, ids 1-40 in order (ScanNet's spelling)
NYU40 = ('wall', 'floor', 'cabinet', 'bed', 'chair', 'sofa', 'table', 'door', 'window', 'bookshelf', 'picture',
         'counter', 'blinds', 'desk', 'shelves', 'curtain', 'dresser', 'pillow', 'mirror', 'floor mat', 'clothes',
         'ceiling', 'books', 'refridgerator', 'television', 'paper', 'towel', 'shower curtain', 'box', 'whiteboard',
         'person', 'night stand', 'toilet', 'sink', 'lamp', 'bathtub', 'bag', 'otherstructure', 'otherfurniture',
         'otherprop')

#: the detectors' classes (the simulator's kinds) in NYU40's names
TO_NYU40 = {
    'bed': 'bed', 'sofa': 'sofa', 'table': 'table', 'desk': 'desk', 'cabinet': 'cabinet',
    'bookshelf': 'bookshelf', 'wardrobe': 'cabinet', 'tv_stand': 'otherfurniture', 'armchair': 'chair',
    'nightstand': 'night stand', 'stool': 'chair', 'bin': 'otherprop', 'plant': 'otherprop', 'chair': 'chair',
    'lamp': 'lamp', 'box': 'box', 'books': 'books', 'vase': 'otherprop', 'monitor': 'television', 'bowl': 'otherprop',
    'tv': 'television'}


def parse_label_map(entries) -> dict:
    """``'FROM:TO,FROM:TO'`` (or a list of entries) -> {FROM: TO}; ValueError saying which
    entry is wrong and why."""
    if isinstance(entries, str):
        entries = [e for e in entries.split(',') if e.strip()]
    out = {}
    known = set(TO_NYU40) | set(NYU40)
    for entry in entries or ():
        name, sep, to = str(entry).partition(':')
        name, to = name.strip(), to.strip()
        if not sep or not name or not to:
            raise ValueError(f"label_map entry '{entry}' is not FROM:TO (e.g. 'monitor:monitor')")
        if name not in known:
            raise ValueError(f"label_map entry '{entry}': '{name}' is neither a detector class "
                             f"({', '.join(sorted(TO_NYU40))}) nor an NYU40 name")
        if name in out and out[name] != to:
            raise ValueError(f"label_map names '{name}' twice ({out[name]}, {to})")
        out[name] = to
    return out


class LabelMap:
    """A detector's class name -> the published name: the user's entry for the class, else
    the user's entry for its NYU40 name, else its NYU40 name. Names it does not know (another
    backend's, an NYU40 name already) pass through the user's entries unchanged otherwise."""

    def __init__(self, entries=()):
        self.renames = parse_label_map(entries)

    def __call__(self, label: str) -> str:
        if not label:
            return label
        if label in self.renames:
            return self.renames[label]
        nyu = TO_NYU40.get(label, label)
        return self.renames.get(nyu, nyu)

    def names(self, labels) -> list:
        return [self(label) for label in labels]


@lru_cache(maxsize=8)
def label_map(entries: str = '') -> LabelMap:
    """The :class:`LabelMap` of a ``label_map`` parameter value (parsed once)."""
    return LabelMap(entries)
