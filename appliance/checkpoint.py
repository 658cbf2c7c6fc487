"""Resume checkpoints for lossless (file) sources: the whole tracker and measures state at a
period boundary, pickled, tied to the code and configuration that made it."""

from __future__ import annotations

import hashlib
import logging
import pickle
import zlib
from functools import cache
from pathlib import Path
from typing import Any

log = logging.getLogger("roadwatch.service")


@cache
def code_fingerprint() -> str:
    """Identifies the code whose objects a checkpoint pickles (others' checkpoints are not resumed)."""
    h = hashlib.sha1()
    for f in sorted(Path(__file__).parent.glob("*.py")):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def pack(key: list, seq: int, frames: int, pipeline: Any, measures: Any) -> bytes:
    return zlib.compress(pickle.dumps({"key": [code_fingerprint(), *key], "seq": seq, "frames": frames,
                                       "pipeline": pipeline, "measures": measures}, protocol=5), 1)


def unpack(blob: bytes | None, key: list) -> dict | None:
    """The checkpoint dict (seq, frames, pipeline, measures), or None if absent or not for this code/config."""
    if blob is None:
        return None
    try:
        ck = pickle.loads(zlib.decompress(blob))
    except Exception as e:  # noqa: BLE001 - a checkpoint from another version: start over
        log.warning("resume checkpoint not usable (%s); processing from the start", e)
        return None
    if ck.get("key") != [code_fingerprint(), *key]:
        log.info("resume checkpoint is for other code, source or site; processing from the start")
        return None
    return ck
