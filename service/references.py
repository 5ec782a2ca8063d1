"""The reference images a scene keeps: what refinement refines on and what edits re-select in.

Artifact ``references.npz``: uint8 ERP arrays ``image_a``, ``image_b`` (H x 2H x 3, at the
encoder's input size, what it was fed); the poses are the scene metadata's ``poses.c2w`` (OpenCV).
"""

from __future__ import annotations

import io
import zipfile

import numpy as np

from rasterizer.render import to_uint8

from .errors import ServiceError
from .store import SceneNotFound, SceneStore

#: the reference images a scene keeps for refinement: uint8 ERP arrays ``image_a``, ``image_b``
#: at the encoder's input size (what it was fed)
REFERENCES_ARTIFACT = "references.npz"
#: zlib level of the artifact's members: photographs barely compress; at level 1 m3d_bedroom's two 512 x 1024
#: references take 3.5% more bytes than at np.savez_compressed's level 6, written in two thirds of the time
REFERENCES_COMPRESSLEVEL = 1


class ReferencesMissing(ServiceError):
    status = 409
    code = "references_missing"


def references_bytes(erp_a: np.ndarray, erp_b: np.ndarray) -> bytes:
    """The ``references.npz`` artifact of two ERP images (uint8, or float in [0, 1])."""
    def u8(img):
        a = np.asarray(img)
        return a if a.dtype == np.uint8 else to_uint8(a)

    buf = io.BytesIO()  # np.savez_compressed's layout (deflated .npy members), at REFERENCES_COMPRESSLEVEL
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, allowZip64=True, compresslevel=REFERENCES_COMPRESSLEVEL) as z:
        for name, img in (("image_a", erp_a), ("image_b", erp_b)):
            with z.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, u8(img), allow_pickle=False)
    return buf.getvalue()


def store_references(store: SceneStore, scene_id: str, erp_a: np.ndarray, erp_b: np.ndarray) -> None:
    """Attach the two reference ERP images to an already stored scene (atomic)."""
    store.put_artifact(scene_id, REFERENCES_ARTIFACT, references_bytes(erp_a, erp_b))


def has_references(store: SceneStore, scene_id: str) -> bool:
    return store.artifact(scene_id, REFERENCES_ARTIFACT) is not None


def references_artifact(store: SceneStore, scene_id: str) -> bytes:
    """The scene's ``references.npz`` bytes; 404 when the scene is gone, 409 when it keeps no references."""
    path = store.artifact(scene_id, REFERENCES_ARTIFACT)
    try:
        if path is not None:
            return path.read_bytes()
    except FileNotFoundError:
        pass
    if not store.exists(scene_id):
        raise SceneNotFound(scene_id)
    raise ReferencesMissing(f"scene {scene_id} has no stored reference images ({REFERENCES_ARTIFACT}); "
                            "refinement, edits and rig renders need them")


def load_references(store: SceneStore, scene_id: str) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """([erp_a, erp_b] uint8, [c2w_a, c2w_b] 4x4 OpenCV) of a stored scene; 409 when not kept."""
    with np.load(io.BytesIO(references_artifact(store, scene_id)), allow_pickle=False) as z:
        images = [z["image_a"], z["image_b"]]
    c2w = store.meta(scene_id)["poses"]["c2w"]
    return images, [np.asarray(m, dtype=np.float64) for m in c2w]
