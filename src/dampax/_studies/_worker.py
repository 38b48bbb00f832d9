"""A local worker of a multi-process error map (``dampax._studies._distributed.run_local``
starts it; its command imports this module, which imports ``dampax`` first: float64 and the
compilation cache, as in the caller).

Kept apart from ``_distributed`` (which the map imports) so that the map's module graph has no
cycle: this module sits above both.
"""

from __future__ import annotations

import json
import os
import sys
import traceback
from pathlib import Path

from .._io import atomic_path
from ._distributed import DistributedError, _give_up, _watch_parent, initialize
from ._maps import error_map


def worker(path: str) -> int:
    """One local worker: join the run, compute its share, process 0 writes the map."""
    job = json.loads(Path(path).read_text())
    _watch_parent()
    import pickle

    import numpy as np

    try:
        initialize(job["coordinator"], job["process_id"], job["num_processes"],
                   timeout=job["timeout"], bind=job["coordinator"], on_timeout=_give_up)
        kwargs = job["kwargs"]
        for key in ("d0_ratio", "d1_ratio", "d2_ratio", "phi0", "k3_ratio"):
            if kwargs.get(key) is not None:
                kwargs[key] = np.asarray(kwargs[key], dtype=float)
        kwargs["models"] = tuple(kwargs["models"])
        ds = error_map(**kwargs, timeout=job["timeout"])
        if job["output"] is not None:  # the Dataset itself: nothing lost on the way back
            with atomic_path(job["output"]) as tmp, open(tmp, "wb") as f:
                pickle.dump(ds, f, protocol=pickle.HIGHEST_PROTOCOL)
    except DistributedError as err:
        _give_up(str(err))
    except BaseException:  # noqa: BLE001 - at once: jax's exit would wait for the others
        traceback.print_exc()
        sys.stderr.flush()
        os._exit(1)
    return 0
