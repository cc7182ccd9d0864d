"""``lmgs-eval weights``: where metric weights live, and importing those supplied by the user (nothing is downloaded)."""

from __future__ import annotations

import argparse
import json

HELP = ("show where metric weights are kept; import weights you have (e.g. the official SyncNet syncnet_v2.model) "
        "into the cache as ONNX")


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION")
    s = sub.add_parser("import-syncnet", help="convert syncnet_python's syncnet_v2.model state dict to ONNX")
    s.add_argument("path", help="syncnet_v2.model (a torch state dict of SyncNetModel S)")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    if args.action == "import-syncnet":
        from lmgs_eval.metrics.sync.nets import import_syncnet

        print(json.dumps(import_syncnet(Path(args.path)), indent=2))
        return 0
    from lmgs_eval.metrics.ort import onnx_cache_dir
    from lmgs_eval.metrics.sync.landmark import JSON_NAME, ONNX_NAME
    from lmgs_eval.metrics.sync.mesh import JSON_NAME as MESH_JSON, ONNX_NAME as MESH_ONNX
    from lmgs_eval.metrics.sync.scorers import PIXEL_JSON, PIXEL_ONNX, WEIGHTS, syncnet_manifest_path
    from lmgs_eval.metrics.sync.select import status

    mp = syncnet_manifest_path()
    print(f"weights cache: {mp.parent}  (imported weights' manifests; ONNX graphs in {onnx_cache_dir()})")
    print(f"  syncnet-v2: {'imported, ' + str(mp) if mp.is_file() else 'not imported (lmgs-eval weights import-syncnet syncnet_v2.model)'}")
    print(f"bundled weights: {WEIGHTS}")
    print(f"  mesh-sync: {WEIGHTS / MESH_ONNX} {'(present)' if (WEIGHTS / MESH_JSON).is_file() else '(missing)'}")
    print(f"  landmark-sync: {WEIGHTS / ONNX_NAME} {'(present)' if (WEIGHTS / JSON_NAME).is_file() else '(missing)'}")
    print(f"  bundled-sync (pixel): {WEIGHTS / PIXEL_ONNX} {'(present)' if (WEIGHTS / PIXEL_JSON).is_file() else '(missing)'}")
    print(f"sync scorer here: {status()[1]}")
    return 0
