"""Runs a `socialflow export-onnx` model with onnxruntime on its check file (stored
observations with burn's actions) and compares: exit 0 when every action is within the
tolerance. Usage: check_onnx.py MODEL [TOLERANCE]. Prints one JSON line."""

import json
import sys

import numpy as np
import onnxruntime as ort


def main():
    model = sys.argv[1]
    tol = float(sys.argv[2]) if len(sys.argv) > 2 else 1e-4
    with open(model + ".check.json") as f:
        check = json.load(f)
    sess = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    names = [i.name for i in sess.get_inputs()]
    feeds = {}
    for name in names:
        block = check["inputs"][name]
        dtype = np.int64 if block.get("dtype") == "int64" else np.float32
        feeds[name] = np.asarray(block["data"], dtype=dtype).reshape(block["shape"])
    (got,) = sess.run(["action"], feeds)
    want = np.asarray(check["action"]["data"], np.float32).reshape(check["action"]["shape"])
    diff = float(np.max(np.abs(got - want)))
    ok = got.shape == want.shape and diff <= tol
    print(json.dumps({"inputs": names, "observations": int(want.shape[0]), "max_abs_diff": diff, "tolerance": tol, "ok": ok}))
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
