"""Level pytrees as flat, named leaves: `LevelSpec` records each leaf's key path ("units.health"),
shape and dtype, and converts between pytrees (or dicts keyed by key path) and the ordered leaf
lists the buffer stores. Generic over any pytree of fixed-shape arrays (dicts, tuples, flax
struct dataclasses such as `tabx.params.EnvParams`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

ROOT_PATH = "_"  # the name of the single leaf of a level that is one bare array


def path_str(path: tuple[Any, ...]) -> str:
    """A key path as a dotted string: `units.health`, `zones.0`, `_` for the root."""
    parts = []
    for key in path:
        if isinstance(key, jax.tree_util.GetAttrKey):
            parts.append(key.name)
        elif isinstance(key, jax.tree_util.DictKey):
            parts.append(str(key.key))
        elif isinstance(key, jax.tree_util.SequenceKey):
            parts.append(str(key.idx))
        elif isinstance(key, jax.tree_util.FlattenedIndexKey):
            parts.append(str(key.key))
        else:  # a custom key type: its str() is the best name we have
            parts.append(str(key))
    return ".".join(parts) if parts else ROOT_PATH


def named_leaves(tree: Any) -> dict[str, Any]:
    """{key path string: leaf} in flattening order; a dict keyed by path strings maps to itself."""
    out: dict[str, Any] = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        name = path_str(path)
        if name in out:
            raise ValueError(f"two leaves of the level share the key path {name!r}")
        out[name] = leaf
    return out


@dataclass(frozen=True)
class LevelSpec:
    """Names, shapes and dtypes of a level's leaves, plus the treedef to rebuild it (None when
    the spec was read from a file without a template: levels are then dicts keyed by path)."""

    paths: tuple[str, ...]
    shapes: tuple[tuple[int, ...], ...]
    dtypes: tuple[np.dtype, ...]
    treedef: Any = None

    @classmethod
    def from_template(cls, level: Any) -> LevelSpec:
        """The spec of one (unbatched) level; host numpy dtypes, so int64 stays int64."""
        leaves = named_leaves(level)
        if not leaves:
            raise ValueError("the template level has no array leaves")
        arrays = {k: np.asarray(v) for k, v in leaves.items()}
        for name, arr in arrays.items():
            if arr.dtype.kind not in "biuf":
                raise ValueError(f"leaf {name!r} has dtype {arr.dtype}; levels hold bool, int "
                                 "or float arrays only")
        treedef = jax.tree_util.tree_structure(level)
        return cls(tuple(arrays), tuple(a.shape for a in arrays.values()),
                   tuple(a.dtype for a in arrays.values()), treedef)

    def to_header(self) -> list[dict[str, Any]]:
        return [{"path": p, "shape": list(s), "dtype": d.str}
                for p, s, d in zip(self.paths, self.shapes, self.dtypes, strict=True)]

    @classmethod
    def from_header(cls, leaves: list[dict[str, Any]]) -> LevelSpec:
        return cls(tuple(str(x["path"]) for x in leaves),
                   tuple(tuple(int(n) for n in x["shape"]) for x in leaves),
                   tuple(np.dtype(str(x["dtype"])) for x in leaves))

    def differences(self, stored: LevelSpec) -> list[str]:
        """How `stored` (read from a file) differs from this spec (a template's); empty when
        they describe the same leaves."""
        out = []
        mine, theirs = set(self.paths), set(stored.paths)
        if mine - theirs:
            out.append(f"template leaves missing from the file: {sorted(mine - theirs)}")
        if theirs - mine:
            out.append(f"file leaves not in the template: {sorted(theirs - mine)}")
        stored_by = {p: (s, d) for p, s, d in zip(stored.paths, stored.shapes, stored.dtypes,
                                                  strict=True)}
        for p, s, d in zip(self.paths, self.shapes, self.dtypes, strict=True):
            if p in stored_by and stored_by[p] != (s, d):
                fs, fd = stored_by[p]
                out.append(f"leaf {p!r}: file has shape {fs} dtype {fd}, template has shape "
                           f"{s} dtype {d}")
        return out

    def flatten_batch(self, levels: Any, what: str = "levels") -> tuple[list[np.ndarray], int]:
        """Leaves of a batch (leading axis B on every leaf) in spec order, cast to the spec
        dtypes; raises ValueError naming the leaf when the structure or a shape is wrong."""
        named = named_leaves(levels)
        if set(named) != set(self.paths):
            missing = sorted(set(self.paths) - set(named))
            extra = sorted(set(named) - set(self.paths))
            raise ValueError(f"{what} do not match the buffer's level structure "
                             f"(missing {missing}, unexpected {extra})")
        out, batch = [], None
        for p, shape, dtype in zip(self.paths, self.shapes, self.dtypes, strict=True):
            arr = np.asarray(named[p])
            if arr.ndim != len(shape) + 1 or arr.shape[1:] != shape:
                raise ValueError(f"{what}: leaf {p!r} has shape {arr.shape}, expected "
                                 f"(batch, {', '.join(map(str, shape))})")
            if batch is None:
                batch = arr.shape[0]
            elif arr.shape[0] != batch:
                raise ValueError(f"{what}: leaf {p!r} has batch size {arr.shape[0]}, "
                                 f"other leaves {batch}")
            if arr.dtype != dtype:
                if not np.can_cast(arr.dtype, dtype, casting="same_kind"):
                    raise ValueError(f"{what}: leaf {p!r} has dtype {arr.dtype}, which does not "
                                     f"convert to {dtype}")
                arr = arr.astype(dtype)
            out.append(arr)
        assert batch is not None
        return out, batch

    def unflatten(self, leaves: list[np.ndarray]) -> Any:
        """A pytree like the template, or a dict keyed by path when there is no template."""
        if self.treedef is None:
            return dict(zip(self.paths, leaves, strict=True))
        # The treedef's leaf order may differ from the spec order (a spec read from a file).
        by_name = dict(zip(self.paths, leaves, strict=True))
        order = [path_str(p) for p in _treedef_paths(self.treedef)]
        return jax.tree_util.tree_unflatten(self.treedef, [by_name[n] for n in order])

    def with_template(self, level: Any) -> tuple[LevelSpec, dict[str, Any]]:
        """This spec (read from a file) checked against a template and given its treedef, and
        the leaves the file lacks that the template's `file_defaults` fill: {path: value}.
        The spec then lists those leaves after the file's."""
        template = LevelSpec.from_template(level)
        defaults = file_defaults(level)
        filled = {p: defaults[p] for p in template.paths
                  if p not in self.paths and p in defaults}
        stored = self
        if filled:
            index = {p: i for i, p in enumerate(template.paths)}
            stored = LevelSpec((*self.paths, *filled),
                               (*self.shapes, *(template.shapes[index[p]] for p in filled)),
                               (*self.dtypes, *(template.dtypes[index[p]] for p in filled)))
        diffs = template.differences(stored)
        if diffs:
            raise ValueError("; ".join(diffs))
        return LevelSpec(stored.paths, stored.shapes, stored.dtypes, template.treedef), filled


def file_defaults(level: Any) -> dict[str, Any]:
    """Leaves of a level that files written before the leaf existed lack, with the value that
    gives such a level its old meaning: the level's class names them as `FILE_DEFAULTS`
    ({key path: value}; `tabx.params.EnvParams`). Other missing leaves stay an error."""
    return dict(getattr(type(level), "FILE_DEFAULTS", None) or {})


def _treedef_paths(treedef: Any) -> list[tuple[Any, ...]]:
    dummy = jax.tree_util.tree_unflatten(treedef, [0] * treedef.num_leaves)
    return [p for p, _ in jax.tree_util.tree_flatten_with_path(dummy)[0]]
