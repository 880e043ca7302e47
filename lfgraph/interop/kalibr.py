"""``kalibr`` (export, import): Kalibr's ``camchain.yaml``, read and written with PyYAML.

``cam0 .. camN-1`` in row-major view order, each with ``camera_model: pinhole``, ``intrinsics: [fu, fv, pu, pv]``,
``distortion_model: radtan``, ``distortion_coeffs: [k1, k2, p1, p2]``, ``resolution: [w, h]`` and a ``rostopic``;
``cam1 ..`` also hold ``T_cn_cnm1`` (4x4), which maps points of camera n-1 into camera n:
``view_T_ref(n) @ inv(view_T_ref(n-1))``. Kalibr stores neither grid nor reference, so import needs ``grid``; the
chain is re-expressed relative to the grid's reference view (view 0 when ``grid`` is a plain ``(rows, cols)``).

Export writes what Kalibr's own ``yaml.dump`` writes: block mappings, lists of numbers in flow style and
``T_cn_cnm1`` as a block list of flow rows; PyYAML writes every float with a ``.`` (``1.0e-05``), so YAML 1.1
readers such as Kalibr's read it back as a float. Import takes any YAML (block or flow lists, comments, a ``---``
start); other keys Kalibr writes (``cam_overlaps``, ``timeshift_cam_imu``, ``T_cam_imu``, ...) are ignored.
``distortion_model: none`` is read as zero distortion; ``equidistant`` and ``fov`` are refused, as are other
camera models (``omni``, ...). A key given twice is refused (PyYAML would keep the last silently).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import Intrinsics
from lfgraph.core.files import write_text_atomic
from lfgraph.core.geometry import invert_T
from lfgraph.interop.common import (
    GridLike,
    array,
    build,
    fail,
    fit_grid,
    intrinsics,
    load_yaml,
    read_text,
    required_grid,
    transform,
    whole,
)

KALIBR_DISTORTION_MODELS = ("radtan", "equidistant", "none")
KALIBR_CAMERA_MODELS = ("pinhole", "omni")  # pinhole-radtan, pinhole-equi (lfgraph fisheye), omni-radtan (unified)
_CAM_KEY = re.compile(r"cam(\d+)")


def _floats(values: Any) -> list[float]:
    """Plain Python floats (PyYAML's safe dumper refuses numpy scalars)."""
    return [float(v) for v in values]


def camchain(calib: Calibration) -> dict[str, dict[str, Any]]:
    """The camchain as the mapping Kalibr reads (``cam0``, ``cam1``, ...), in view order."""
    chain: dict[str, dict[str, Any]] = {}
    for v in range(calib.num_views):
        intr = calib.intrinsics[v]
        cam: dict[str, Any] = {}
        if v > 0:
            # view_T_ref(v) @ inv(view_T_ref(v - 1)), with inv(view_T_ref) = ref_T_view already at hand
            cn_T_cnm1 = calib.view_T_ref(v) @ calib.ref_T_view[v - 1]  # noqa: N806
            cn_T_cnm1[3] = [0.0, 0.0, 0.0, 1.0]
            cam["T_cn_cnm1"] = [_floats(row) for row in cn_T_cnm1]
        fisheye, unified = intr.lens == "fisheye", intr.lens == "unified"
        cam |= {
            "camera_model": "omni" if unified else "pinhole",
            "intrinsics": _floats(([intr.xi] if unified else []) + [intr.fx, intr.fy, intr.cx, intr.cy]),
            "distortion_model": "equidistant" if fisheye else "radtan",
            "distortion_coeffs": _floats([intr.k1, intr.k2, intr.k3, intr.k4] if fisheye
                                         else [intr.k1, intr.k2, intr.p1, intr.p2]),
            "resolution": [int(x) for x in calib.image_size(v)],  # each view's own (a rig of mixed sizes)
            "rostopic": f"/lfgraph/{calib.grid.name(v)}/image_raw",
        }
        chain[f"cam{v}"] = cam
    return chain


def write(calib: Calibration, path: Path) -> None:
    """Write ``calib`` as a Kalibr ``camchain.yaml`` (cam0 = view 0, row-major; ``T_cn_cnm1`` chain in metres),
    atomically."""
    header = (f"# Kalibr camera chain written by lfgraph: {calib.grid} grid, views row-major (cam0 = view 0), "
              f"reference view {calib.grid.reference}\n"
              "# T_cn_cnm1 maps points of camera n-1 into camera n (metres)\n")
    # default_flow_style=None: lists of scalars in flow style, the rest block style, as Kalibr's yaml.dump writes
    body = yaml.safe_dump(camchain(calib), default_flow_style=None, sort_keys=False, width=1_000_000)
    write_text_atomic(path, header + body)


def read(path: Path, grid: GridLike) -> Calibration:
    """Read a Kalibr ``camchain.yaml`` (cam0, cam1, ... in row-major order) as a calibration on ``grid`` (required:
    Kalibr stores no grid)."""
    data = load_yaml(read_text(path), path)
    if not isinstance(data, dict):
        raise fail(path, "file", "must be a YAML mapping of cameras (cam0, cam1, ...)")
    cams = sorted(int(m.group(1)) for k in data if isinstance(k, str) and (m := _CAM_KEY.fullmatch(k)))
    if not cams:
        raise fail(path, "cam0", "is missing (no camN entries)")
    n = len(cams)
    for i in range(n):
        if f"cam{i}" not in data:
            raise fail(path, f"cam{i}", f"is missing (found {', '.join(f'cam{c}' for c in cams)})")
    ref_grid = required_grid(grid, n, path, "cam*", reference=0)

    def get(cam: str, key: str) -> Any:
        entry = data[cam]
        if not isinstance(entry, dict):
            raise fail(path, cam, "must be a mapping")
        if key not in entry:
            raise fail(path, f"{cam}.{key}", "is missing")
        return entry[key]

    views: list[Intrinsics] = []
    sizes: list[tuple[int, int]] = []
    cn_T_c0 = [np.eye(4)]  # noqa: N806 - camera n from camera 0, chained
    for i in range(n):
        cam = f"cam{i}"
        model = get(cam, "camera_model")
        if model not in KALIBR_CAMERA_MODELS:
            raise fail(path, f"{cam}.camera_model", f"must be one of {', '.join(KALIBR_CAMERA_MODELS)}, got {model!r}")
        xi = None
        if model == "omni":
            xi, fu, fv, pu, pv = array(get(cam, "intrinsics"), (5,), path, f"{cam}.intrinsics")
        else:
            fu, fv, pu, pv = array(get(cam, "intrinsics"), (4,), path, f"{cam}.intrinsics")
        dist_model = get(cam, "distortion_model")
        if dist_model not in KALIBR_DISTORTION_MODELS or (xi is not None and dist_model == "equidistant"):
            raise fail(path, f"{cam}.distortion_model", f"must be one of {', '.join(KALIBR_DISTORTION_MODELS)} "
                                                        f"(omni with radtan or none), got {dist_model!r}")
        dist = np.zeros(4) if dist_model == "none" else array(get(cam, "distortion_coeffs"), (4,), path,
                                                              f"{cam}.distortion_coeffs")
        K = np.array([[fu, 0.0, pu], [0.0, fv, pv], [0.0, 0.0, 1.0]])  # noqa: N806
        if xi is not None:
            try:
                views.append(Intrinsics(fu, fv, pu, pv, *dist, xi=xi, lens="unified"))
            except ValueError as exc:
                raise fail(path, f"{cam}.intrinsics", str(exc)) from None
        else:
            views.append(intrinsics(path, f"{cam}.intrinsics", K, dist,
                                    "fisheye" if dist_model == "equidistant" else "radtan"))
        res = array(get(cam, "resolution"), (2,), path, f"{cam}.resolution")
        sizes.append((whole(res[0], path, f"{cam}.resolution"), whole(res[1], path, f"{cam}.resolution")))
        if i > 0:
            key = f"{cam}.T_cn_cnm1"
            T = transform(array(get(cam, "T_cn_cnm1"), (4, 4), path, key), path, key)  # noqa: N806
            cn_T_c0.append(T @ cn_T_c0[-1])
    ref = ref_grid.reference
    c0_T_ref = invert_T(cn_T_c0[ref])  # noqa: N806
    # ref_T_view = inv(view_T_c0 @ c0_T_ref)
    ref_T_view = np.stack([invert_T(cn_T_c0[v] @ c0_T_ref) for v in range(n)])  # noqa: N806
    ref_T_view[ref] = np.eye(4)
    calib = build(path, "cam*", ref_grid, sizes[ref], views, ref_T_view, sizes)
    return fit_grid(calib, grid, path, "cam*")
