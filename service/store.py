"""On-disk scene store with an in-memory LRU of decoded scenes.

Layout under ``root``::

    scenes/<id>/gaussians.npz   # means, scales (float32); quats, opacities, sh (float16): :data:`STORED_DTYPES`
    scenes/<id>/meta.json       # inputs, poses, options, model, timings, parent...
    scenes/<id>/<artifact>      # references, correspondences, selections (added atomically)
    tmp/                        # scenes being written; leftovers older than tmp_grace_s cleared at start-up
    trash/                      # scenes being deleted; idem

Budget: the scenes together stay within ``budget_bytes`` (0: no cap). A write that would pass it
first evicts the least recently used scenes that no job holds (:meth:`SceneStore.hold`). When
evicting all of them could not make room (the write alone exceeds the budget, or held scenes fill
it), or when the disk would keep less than ``min_free_bytes`` free, the write is refused with
:class:`StoreFull` (the service answers 507) before any eviction: nothing is stored, nothing lost.

A scene is written into ``tmp/<random>/`` (each file fsynced), then renamed to
``scenes/<id>`` in one ``os.replace`` and the parent directory fsynced: a crash leaves
either no scene or a whole one, never half. Ids are content hashes (see
:func:`content_id`), so two writers of one id write the same thing and the second one
simply drops its copy. Nothing here knows about HTTP or the model: a derived scene
(e.g. refined from another) is ``store.put(content_id("refine", parent_id, params), ...)``
with ``meta["parent"] = parent_id``.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import logging
import os
import re
import shutil
import threading
import time
import uuid
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Callable

import numpy as np

from rasterizer.gaussians import Gaussians
from rasterizer.lru import LRUCache

log = logging.getLogger("omnisplat.store")

_FIELDS = ("means", "scales", "quats", "opacities", "sh")
#: On-disk dtype of each field. Positions and scales keep float32 (a scene may span kilometres or
#: millimetres, and a scale of 1e-6 m is a float16 subnormal); rotations, opacities and SH colour
#: coefficients are float16 (relative error <= 2**-11): renders move by less than
#: :data:`STORED_RENDER_TOLERANCE` (tests/service/test_store_budget.py checks it).
STORED_DTYPES = {"means": np.float32, "scales": np.float32, "quats": np.float16, "opacities": np.float16,
                 "sh": np.float16}
#: Default cap of the scenes' bytes on disk (``OMNISPLAT_STORE_BUDGET_BYTES``): about 400 scenes of 470k Gaussians.
DEFAULT_BUDGET_BYTES = 16 << 30
#: Default free disk every store write must leave (``OMNISPLAT_MIN_FREE_STORE_BYTES``).
DEFAULT_MIN_FREE_BYTES = 256 << 20
#: Default age (s) below which a start-up leaves unfinished writes (``tmp/``, ``trash/``, artifact ``.tmp`` files)
#: alone (``OMNISPLAT_STORE_TMP_GRACE_S``): another process sharing the store (a second server on the same volume)
#: may be writing them. A write takes seconds; a crash's leftovers go at a start-up after this.
DEFAULT_TMP_GRACE_S = 600.0
#: Times :meth:`SceneStore.put` restarts a write whose staging folder another process removed.
_STAGING_ATTEMPTS = 3
#: Largest change of any rendered pixel (colour in [0, 1]) that storing a scene may cause.
STORED_RENDER_TOLERANCE = 2.0 / 255.0
_META_CACHE = 1024  # metadata dicts kept in memory


#: Scene (and job) ids: 32 lower-case hex digits (a content hash); the store owns this format.
SCENE_ID_PATTERN = r"^[0-9a-f]{32}$"
_SCENE_ID_RE = re.compile(SCENE_ID_PATTERN)


class InvalidSceneId(ValueError):
    """A scene id that is not 32 lower-case hex digits (``..``, slashes, ...)."""


def check_scene_id(scene_id: str) -> str:
    """Return ``scene_id`` if well-formed, else raise :class:`InvalidSceneId`: no path ever leaves the store."""
    if not isinstance(scene_id, str) or not _SCENE_ID_RE.match(scene_id):
        raise InvalidSceneId(f"malformed scene id {str(scene_id)[:80]!r}; expected 32 lower-case hex digits")
    return scene_id


class SceneNotFound(KeyError):
    """No scene with that id in the store."""

    def __init__(self, scene_id: str) -> None:
        super().__init__(scene_id)
        self.scene_id = scene_id

    def __str__(self) -> str:
        return f"no scene with id {self.scene_id!r}"


class StoreCorrupt(RuntimeError):
    """A stored scene cannot be read back (disk damage or outside interference)."""


class StoreWriteRefused(OSError):
    """A store write that did not happen; nothing was written. ``code`` names the reason for the service's
    answer, ``message`` (also ``str()``) says it to the user, ``errno`` is the class's :attr:`ERRNO`."""

    code = "store_write_refused"
    ERRNO = errno.EIO

    def __init__(self, message: str) -> None:
        super().__init__(self.ERRNO, message)
        self.message = message

    def __str__(self) -> str:
        return self.message


class StoreInterrupted(StoreWriteRefused):
    """A write whose staging folder kept vanishing (another process clearing ``tmp/``); nothing was stored,
    and sending it again is expected to work."""

    code = "store_interrupted"
    ERRNO = errno.EAGAIN


class StoreFull(StoreWriteRefused):
    """A write refused by the store's budget or free-space margin; nothing was written.

    An ``ENOSPC`` error, so that any handler of a full disk also handles it; ``code`` and
    ``message`` say which limit refused it.
    """

    code = "store_full"
    ERRNO = errno.ENOSPC


def stored_form(g: Gaussians) -> Gaussians:
    """``g`` as it reads back from the store: each field rounded to its :data:`STORED_DTYPES` dtype."""
    return Gaussians(*(getattr(g, f).astype(STORED_DTYPES[f]) for f in _FIELDS))


def content_id(*parts: bytes | str) -> str:
    """A 32-hex-digit id from a sequence of parts (length-prefixed, so parts cannot run together)."""
    h = hashlib.sha256()
    for part in parts:
        b = part.encode() if isinstance(part, str) else bytes(part)
        h.update(len(b).to_bytes(8, "little"))
        h.update(b)
    return h.hexdigest()[:32]


def canonical_json(obj) -> str:
    """The one JSON text of a request object that ids are hashed from (sorted keys, no spaces)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _age(path: Path) -> float:
    try:
        return time.time() - path.stat().st_mtime
    except OSError:
        return float("inf")


def _tree_bytes(path: Path) -> int:
    """Bytes of the files directly in ``path`` (a scene folder); 0 when it is gone."""
    total = 0
    try:
        with os.scandir(path) as entries:
            for entry in entries:
                with contextlib.suppress(OSError):
                    if entry.is_file(follow_symlinks=False):
                        total += entry.stat(follow_symlinks=False).st_size
    except OSError:
        return 0
    return total


def _write_file(path: Path, writer: Callable[[Any], None]) -> None:
    with open(path, "wb") as f:
        writer(f)
        f.flush()
        os.fsync(f.fileno())


def json_safe(obj: Any) -> Any:
    """Convert numpy scalars/arrays (and Paths) nested in dicts/lists to plain JSON values."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist()) if obj.size <= 64 else f"<array {obj.shape} {obj.dtype}>"
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return str(obj)


def _gaussians_nbytes(g: Gaussians) -> int:
    """Bytes of one scene's Gaussians in the cache (its stored fields)."""
    return sum(getattr(g, f).nbytes for f in _FIELDS)


class SceneStore:
    """Scenes on local disk (durable, atomic) plus a bounded in-memory LRU of their Gaussians."""

    def __init__(self, root: str | Path, *, cache_scenes: int = 8, cache_bytes: int = 1 << 30,
                 max_scenes: int = 0, tmp_grace_s: float = DEFAULT_TMP_GRACE_S,
                 budget_bytes: int = DEFAULT_BUDGET_BYTES, min_free_bytes: int = DEFAULT_MIN_FREE_BYTES,
                 clean_up: bool = True) -> None:
        """``clean_up``: remove unfinished writes older than ``tmp_grace_s`` (a crash's leftovers; 0: all of
        them, only right when no other process uses the store). A client that borrows a server's store (the
        CLI) passes False: it never removes anything it did not write."""
        self.root = Path(root)
        self.scenes_dir = self.root / "scenes"
        self.tmp_dir = self.root / "tmp"
        self.trash_dir = self.root / "trash"
        for d in (self.scenes_dir, self.tmp_dir, self.trash_dir):
            d.mkdir(parents=True, exist_ok=True)
        if clean_up:
            self._clean_up(tmp_grace_s)
        self.max_scenes = max_scenes
        self.budget_bytes = int(budget_bytes)
        self.min_free_bytes = int(min_free_bytes)
        self.cache: LRUCache[str, Gaussians] = LRUCache(cache_scenes, cache_bytes, size=_gaussians_nbytes)
        self._meta_cache: LRUCache[str, dict] = LRUCache(_META_CACHE)  # small: metadata dicts only
        self._lock = threading.Lock()
        self._room = threading.Lock()  # eviction + the write it makes room for happen together
        self._used: dict[str, float] = {}  # scene id -> last use (unix time); absent: the folder's mtime
        self._holds: Counter[str] = Counter()  # scene id -> jobs using it (never evicted meanwhile)
        self.evictions = 0
        self.refusals = 0

    @classmethod
    def from_settings(cls, settings, *, clean_up: bool = True) -> "SceneStore":
        """The store a :class:`service.config.Settings` describes (``clean_up``: see :meth:`__init__`)."""
        return cls(settings.store_dir, cache_scenes=settings.cache_scenes, cache_bytes=settings.cache_bytes,
                   max_scenes=settings.max_scenes, tmp_grace_s=settings.store_tmp_grace_s,
                   budget_bytes=settings.store_budget_bytes, min_free_bytes=settings.min_free_store_bytes,
                   clean_up=clean_up)

    def _clean_up(self, grace_s: float) -> None:
        """Remove unfinished writes (staging folders, trash, artifact ``.tmp`` files) older than ``grace_s``:
        leftovers of a crash, never visible as scenes. Younger ones may be another live process's writes."""
        def stale(path: Path) -> bool:
            return not (grace_s and _age(path) < grace_s)

        for d in (self.tmp_dir, self.trash_dir):
            for child in d.iterdir():
                if stale(child):
                    shutil.rmtree(child, ignore_errors=True) if child.is_dir() else child.unlink(missing_ok=True)
        for folder in self.scenes_dir.iterdir():  # .<name>.<hex>.tmp
            for leftover in folder.glob(".*.tmp") if folder.is_dir() else ():
                if stale(leftover):
                    leftover.unlink(missing_ok=True)

    # -- paths ------------------------------------------------------------------
    def _dir(self, scene_id: str) -> Path:
        return self.scenes_dir / check_scene_id(scene_id)

    def exists(self, scene_id: str) -> bool:
        return (self._dir(scene_id) / "meta.json").is_file()

    def ids(self) -> list[str]:
        """The stored scenes' ids. Folders not named by an id (a copy made by hand, ``lost+found``) are no scenes:
        neither counted against the budget nor ever chosen for eviction, which could not delete them."""
        return sorted(p.name for p in self.scenes_dir.iterdir()
                      if _SCENE_ID_RE.match(p.name) and (p / "meta.json").is_file())

    def count(self) -> int:
        return len(self.ids())

    def usage(self) -> int:
        """Bytes the stored scenes take on disk (every file of every scene folder)."""
        return sum(_tree_bytes(self.scenes_dir / i) for i in self.ids())

    @contextlib.contextmanager
    def hold(self, *scene_ids: str) -> Iterator[None]:
        """Keep ``scene_ids`` from eviction while the block runs (a job reading them); DELETE still removes them."""
        self.acquire(*scene_ids)
        try:
            yield
        finally:
            self.release(*scene_ids)

    def acquire(self, *scene_ids: str) -> None:
        """Keep ``scene_ids`` from eviction until as many :meth:`release` calls (holds count; a queued job's
        parent is held from its submission to its end); DELETE still removes them."""
        with self._lock:
            self._holds.update(scene_ids)

    def release(self, *scene_ids: str) -> None:
        """Drop one :meth:`acquire` of each of ``scene_ids``."""
        with self._lock:
            self._holds.subtract(scene_ids)
            for sid in scene_ids:
                if self._holds[sid] <= 0:
                    del self._holds[sid]

    def held(self) -> dict[str, int]:
        """Scene id -> holds now (jobs queued or running on it)."""
        with self._lock:
            return dict(self._holds)

    def _touch(self, scene_id: str) -> None:
        self._used[scene_id] = time.time()

    def _last_used(self, scene_id: str) -> float:
        used = self._used.get(scene_id)
        if used is not None:
            return used
        try:
            return (self.scenes_dir / scene_id).stat().st_mtime
        except OSError:  # deleted meanwhile: first in line, and delete() then finds nothing
            return float("-inf")

    def _check_margin(self, need: int) -> None:
        """Refuse a write of ``need`` bytes that would leave less than ``min_free_bytes`` on the disk."""
        if self.min_free_bytes <= 0:
            return
        try:
            free = shutil.disk_usage(self.root).free
        except OSError:
            return  # the write itself reports an unreadable store
        if free - need < self.min_free_bytes:
            self.refusals += 1
            raise StoreFull(f"the scene store's disk has {free} bytes free; writing {need} more would leave less "
                            f"than the {self.min_free_bytes}-byte margin; nothing was stored")

    def check_room(self, like: str, what: str) -> None:
        """:class:`StoreFull` now, nothing evicted, when a new scene the size of scene ``like`` could not be
        stored beside the held scenes and ``like`` itself (a refinement's result, checked before it is queued)."""
        need = _tree_bytes(self.scenes_dir / like)
        with self._room:
            self._make_room(need, what=what, also_held=(like,), evict=False)

    def _make_room(self, need: int, keep: str | None = None, what: str = "the new scene", *,
                   also_held: tuple[str, ...] = (), evict: bool = True) -> None:
        """Evict least recently used scenes (not held, not ``keep``) until ``need`` more bytes fit the budget
        and the scene count fits ``max_scenes``; :class:`StoreFull` when they cannot. Call with ``_room`` held.

        Decides first, evicts after: a write that cannot fit even with every evictable scene gone is
        refused with nothing evicted (``what`` names the write in that message). ``also_held``: ids
        counted as held; ``evict=False`` only decides."""
        if self.budget_bytes <= 0 and self.max_scenes <= 0:
            return
        ids = self.ids()
        sizes = {i: _tree_bytes(self.scenes_dir / i) for i in ids} if self.budget_bytes > 0 else {}
        used = sum(sizes.values())
        count = len(ids) + (1 if keep is None else 0)  # a new scene counts once it is renamed in
        with self._lock:
            held = set(self._holds) | set(also_held)
        victims = sorted((i for i in ids if i not in held and i != keep), key=self._last_used)
        kept = [i for i in ids if i in held or i == keep]  # never evicted for this write
        kept_bytes = sum(sizes.get(i, 0) for i in kept)
        if (self.budget_bytes > 0 and kept_bytes + need > self.budget_bytes) or \
                (self.max_scenes > 0 and count - len(victims) > self.max_scenes):
            self.refusals += 1
            if self.budget_bytes > 0 and need > self.budget_bytes:
                raise StoreFull(f"{what} alone takes {need} bytes, more than the scene store's whole budget "
                                f"({self.budget_bytes} bytes); nothing was stored and no scene was evicted")
            if self.budget_bytes > 0 and kept_bytes + need > self.budget_bytes:
                raise StoreFull(f"the scene store's budget ({self.budget_bytes} bytes) cannot take {what} ({need} "
                                f"bytes) beside the {kept_bytes} bytes of {len(kept)} scenes that jobs (or this write) "
                                "are using; nothing was stored and no scene was evicted")
            raise StoreFull(f"the scene store keeps at most {self.max_scenes} scenes and jobs (or this write) are using "
                            f"{len(kept)} of them: {what} cannot be stored beside them; nothing was stored and no "
                            "scene was evicted")
        for victim in victims if evict else ():  # enough of them, by the check above
            if (self.budget_bytes <= 0 or used + need <= self.budget_bytes) and \
                    (self.max_scenes <= 0 or count <= self.max_scenes):
                break
            log.info("store budget: evicting %s (least recently used)", victim)
            if self.delete(victim):
                self.evictions += 1
            count -= 1  # gone either way (another process may have deleted it first)
            used -= sizes.get(victim, 0)

    def write_problem(self, min_free: int = 0) -> str | None:
        """Why the store cannot take a new scene now (not writable, under ``min_free`` bytes free), or None."""
        probe = self.tmp_dir / f".probe-{uuid.uuid4().hex}"
        try:
            _write_file(probe, lambda f: f.write(b"ok"))
            probe.unlink()
            free = shutil.disk_usage(self.root).free
        except OSError as exc:
            with contextlib.suppress(OSError):
                probe.unlink(missing_ok=True)
            return f"the scene store is not writable ({exc.strerror or exc})"
        if free < min_free:
            return f"the scene store's disk has {free} bytes free (less than {min_free})"
        return None

    # -- write --------------------------------------------------------------------
    def put(self, scene_id: str, gaussians: Gaussians, meta: dict, artifacts: dict[str, bytes] | None = None) -> dict:
        """Store a scene atomically and return its metadata (the existing one if the id is taken).

        ``artifacts`` (name -> bytes) are written in the same atomic rename, so a scene
        never exists without them.
        """
        final = self._dir(scene_id)
        if (final / "meta.json").is_file():
            return self.meta(scene_id)
        meta = json_safe({**meta, "id": scene_id, "num_gaussians": len(gaussians),
                          "created_at": meta.get("created_at", time.time())})
        arrays = {f: getattr(gaussians, f).astype(STORED_DTYPES[f], copy=False) for f in _FIELDS}  # float32 ones: no copy
        self._check_margin(sum(a.nbytes for a in arrays.values()) + sum(len(d) for d in (artifacts or {}).values()))
        for name in artifacts or {}:
            if "/" in name or name.startswith(".") or name in ("meta.json", "gaussians.npz"):
                raise ValueError(f"bad artifact name {name!r}")
        files = {"gaussians.npz": lambda f: np.savez(f, **arrays),
                 **{name: (lambda f, data=data: f.write(data)) for name, data in (artifacts or {}).items()},
                 "meta.json": lambda f, text=json.dumps(meta, indent=1, sort_keys=True).encode(): f.write(text)}
        for _ in range(_STAGING_ATTEMPTS):
            staging = self.tmp_dir / f"{scene_id}-{uuid.uuid4().hex}"
            try:
                staging.mkdir(parents=True)
                for name, writer in files.items():
                    _write_file(staging / name, writer)
                _fsync_dir(staging)
                with self._room:
                    if (final / "meta.json").is_file():  # a concurrent writer of the same id won: evict nothing
                        shutil.rmtree(staging, ignore_errors=True)
                        return self.meta(scene_id)
                    self._make_room(_tree_bytes(staging))
                    try:
                        os.replace(staging, final)
                    except OSError:
                        if (final / "meta.json").is_file():  # a concurrent writer of the same id won
                            shutil.rmtree(staging, ignore_errors=True)
                            return self.meta(scene_id)
                        if not final.is_dir():
                            raise
                        # a folder without meta.json is no scene (its metadata lost to damage): it would refuse
                        # every rename into its place, so it goes to the trash and the whole scene takes its place
                        log.warning("store: %s has no meta.json; replacing it with the scene being written", scene_id)
                        self._bury(final)
                        os.replace(staging, final)
                    self._touch(scene_id)
                _fsync_dir(self.scenes_dir)
                break
            except FileNotFoundError:
                if staging.is_dir():
                    shutil.rmtree(staging, ignore_errors=True)
                    raise
                log.warning("store: the staging folder of %s vanished (another process cleared tmp/); writing it again",
                            scene_id)
            except BaseException:
                shutil.rmtree(staging, ignore_errors=True)
                raise
        else:
            raise StoreInterrupted(f"the scene store's staging folder was removed {_STAGING_ATTEMPTS} times while "
                                   "the scene was written (another process is clearing its tmp/); nothing was "
                                   "stored; send it again")
        self.cache.put(scene_id, Gaussians(*arrays.values()))  # what reads back from disk, not the unrounded input
        return meta

    def put_artifact(self, scene_id: str, name: str, data: bytes) -> Path:
        """Atomically add a derived file (e.g. the PLY) to an existing scene."""
        folder = self._dir(scene_id)
        if not folder.is_dir() or "/" in name or name.startswith("."):
            raise SceneNotFound(scene_id)
        target = folder / name
        tmp = folder / f".{name}.{uuid.uuid4().hex}.tmp"
        self._check_margin(len(data))
        try:
            with self._room:
                self._make_room(len(data) - (target.stat().st_size if target.is_file() else 0), keep=scene_id,
                                what=f"the file {name}")
                _write_file(tmp, lambda f: f.write(data))
                os.replace(tmp, target)
        except FileNotFoundError:  # the scene was deleted meanwhile
            raise SceneNotFound(scene_id) from None
        finally:
            tmp.unlink(missing_ok=True)
        self._touch(scene_id)
        return target

    def artifact(self, scene_id: str, name: str) -> Path | None:
        path = self._dir(scene_id) / name
        if not path.is_file():
            return None
        self._touch(scene_id)
        return path

    def delete(self, scene_id: str) -> bool:
        """Remove a scene; it disappears in one rename, the files go afterwards."""
        folder = self._dir(scene_id)
        self.cache.drop(scene_id)
        self._meta_cache.drop(scene_id)
        self._used.pop(scene_id, None)
        return self._bury(folder)

    def _bury(self, folder: Path) -> bool:
        """Rename ``folder`` (a scene's) into ``trash/`` and remove it there; False when it is not there."""
        grave = self.trash_dir / f"{folder.name}-{uuid.uuid4().hex}"
        try:
            os.replace(folder, grave)
        except FileNotFoundError:
            if not folder.is_dir():
                return False
            self.trash_dir.mkdir(parents=True, exist_ok=True)  # trash/ itself removed (by hand) since start-up
            os.replace(folder, grave)
        _fsync_dir(self.scenes_dir)
        shutil.rmtree(grave, ignore_errors=True)
        return True

    # -- read -------------------------------------------------------------------
    def meta(self, scene_id: str) -> dict:
        cached = self._meta_cache.get(scene_id)
        if cached is not None and self.exists(scene_id):
            return cached
        path = self._dir(scene_id) / "meta.json"
        try:
            meta = json.loads(path.read_text())
        except FileNotFoundError:
            raise SceneNotFound(scene_id) from None
        except ValueError as exc:
            raise StoreCorrupt(f"scene {scene_id}: meta.json unreadable ({exc})") from None
        count = meta.get("num_gaussians") if isinstance(meta, dict) else None
        if not isinstance(meta, dict) or meta.get("id") != scene_id or not isinstance(count, int) or count < 0:
            # readable JSON, but not what put() wrote for this id: another scene's file, or damage
            found = f"the id {str(meta.get('id'))[:40]!r}" if isinstance(meta, dict) else f"a JSON {type(meta).__name__}"
            raise StoreCorrupt(f"scene {scene_id}: meta.json holds {found}, not this scene's metadata")
        self._meta_cache.put(scene_id, meta)
        return meta

    def gaussians(self, scene_id: str) -> Gaussians:
        """The scene's Gaussians as stored (from the cache, else read and cached); :class:`StoreCorrupt` when the
        file cannot be read or holds another count than the scene's metadata (another scene's file)."""
        g = self.cache.get(check_scene_id(scene_id))
        if g is not None:
            self._touch(scene_id)
            return g
        path = self._dir(scene_id) / "gaussians.npz"
        try:
            with np.load(path, allow_pickle=False) as z:
                g = Gaussians(*(z[f] for f in _FIELDS))
        except FileNotFoundError:
            raise SceneNotFound(scene_id) from None
        except Exception as exc:  # noqa: BLE001 - zip/shape errors all mean a damaged file
            raise StoreCorrupt(f"scene {scene_id}: gaussians.npz unreadable ({exc})") from None
        if len(g) != self.meta(scene_id)["num_gaussians"]:
            raise StoreCorrupt(f"scene {scene_id}: gaussians.npz holds {len(g)} Gaussians, its metadata "
                               f"{self.meta(scene_id)['num_gaussians']}: not this scene's file")
        self._touch(scene_id)
        self.cache.put(scene_id, g)
        return g
