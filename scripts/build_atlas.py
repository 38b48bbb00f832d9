"""Build the error atlas shipped with dampax (src/dampax/data/error_atlas.nc).

    python scripts/build_atlas.py            # about a minute on 2 CPU cores

The atlas is `dampax.error_map` (the diffrax reference, 20 undamped periods, 64 samples per
period) over a grid of the dimensionless ratios d0/(w0 A0), d1/w0, d2 A0/w0 and the initial
phase phi0 in [0, pi) (phi0 + pi is the mirror-image motion, with the same errors), for every
analytic model. Only max_error is kept (float32), with the grid and the settings as attributes;
`dampax._models._atlas` interpolates it for `solution.error_estimate` and `method="auto"`.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

#: The atlas grid (kept here, in one place; the file records it).
GRID = dict(d0_ratio=np.linspace(0.0, 0.2, 17), d1_ratio=np.linspace(0.0, 0.4, 9),
            d2_ratio=np.linspace(0.0, 1.0, 17),
            phi0=np.linspace(0.0, math.pi, 16, endpoint=False))
MODELS = ("matched", "undamped", "matched_tail", "rizcallah", "coulomb_exact")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "src"
                   / "dampax" / "data" / "error_atlas.nc")
    args = p.parse_args()
    import dampax as dp

    ds = dp.error_map(**GRID, models=MODELS, periods=20.0, samples_per_period=64,
                      chunk_size=256)
    atlas = ds[["max_error"]].astype("float32")
    atlas["max_error"].attrs.update(ds["max_error"].attrs)
    atlas.attrs = {k: v for k, v in ds.attrs.items() if k != "history"}
    atlas.attrs["title"] = "dampax error atlas: max |x - x_ref| / A0 of every analytic model"
    atlas.attrs["built_by"] = "python scripts/build_atlas.py"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    from dampax._io import write_netcdf

    write_netcdf(atlas, args.out)  # CF: no _FillValue on the coordinates
    print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.0f} KiB, "
          f"{int(np.prod([v.size for v in GRID.values()]))} points x {len(MODELS)} models)")


if __name__ == "__main__":
    main()
