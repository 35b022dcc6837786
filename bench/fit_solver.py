"""The body fit's own Levenberg-Marquardt against scipy's MINPACK least_squares (issue 50), on
the eval scenes' fits: each solve of stages 2 and 3 runs both from the same start, and the
final costs are compared (the pipeline goes on with ours).

    python bench/fit_solver.py data/evalval512 data/eval512
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from scene_run import replaced, run_scene  # noqa: E402

from relightcli.evaluate import find_scenes  # noqa: E402
from relightcli.geometry import body_fit  # noqa: E402
from relightcli.pipeline import RelightOptions  # noqa: E402
from relightcli.stages.frame import Models  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+", help="eval scene folders (true masks used)")
    args = parser.parse_args()
    ours, rows = body_fit.levenberg_marquardt, []

    def both(fun, jac, x, evaluations):
        mine = ours(fun, jac, x, evaluations)
        minpack = least_squares(fun, x, jac=jac, method="lm", max_nfev=evaluations, x_scale="jac").x
        rows.append((evaluations, *(float(fun(v) @ fun(v)) for v in (mine, minpack))))
        return mine

    models = Models(2, 512)
    options = RelightOptions(outputs=("body_normal",), method="sh9", threads=2)
    with replaced(body_fit, "levenberg_marquardt", both):
        for folder in (f for scenes in args.scenes for f in find_scenes(Path(scenes))):
            run_scene(folder, options, models)
    table = np.array(rows)
    for evaluations, stage in ((20, "stage 2"), (15, "stage 3")):
        mine, minpack = table[table[:, 0] == evaluations, 1:].T
        print(f"{stage}: {mine.size} fits, cost ours / scipy's median {np.median(mine / minpack):.4f}, "
              f"lower in {(mine < minpack).sum()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
