"""Independent check of triax-modal: the same windows through pyOMA2's SSI-cov.

Usage: pyoma2_check.py <dir>. `<dir>/windows.json` lists the windows the Rust test wrote
(`{"windows": [{"file", "samples", "channels", "sample_rate_hz", "block_rows", "max_order",
"blocks", "frequencies_hz"}]}`), each `file` the building-frame channels after Triax's
decimation, float64 little-endian, sample-major (samples × channels). For each window, pyOMA2
(PyPI `pyOMA-2`) runs SSI-cov with its own Hankel matrix, its own stabilisation labels and its
own first-order uncertainty (`calc_unc`, over `blocks` segments); for each of
`frequencies_hz` the script takes a pole pyOMA2 labels stable within 0.5 % (so that it cannot
take the other mode of a close pair, 1.5 % away). Writes `<dir>/pyoma2.json`: per window, per
frequency asked, `frequency_hz`, `frequency_std_hz`, `damping_ratio`, `damping_std`,
`shape_real`, `shape_imag` (null where pyOMA2 has no stable pole there).

Exits with status 2 and says so when pyOMA2 is not installed: the test must not pass
without it.
"""

import json
import logging
import os
import sys
import warnings

import numpy as np

try:
    from pyoma2.algorithms import SSI
    from pyoma2.setup import SingleSetup
except ImportError as e:  # the Rust test turns this into a failure naming the package
    print(f"pyOMA2 is not importable ({e}): pip install pyOMA-2 "
          "(examples/python/requirements.txt)", file=sys.stderr)
    sys.exit(2)

logging.disable(logging.WARNING)
warnings.filterwarnings("ignore")


def identify(window, directory):
    data = np.fromfile(os.path.join(directory, window["file"]), dtype="<f8")
    data = data.reshape(window["samples"], window["channels"])
    setup = SingleSetup(data, fs=window["sample_rate_hz"])
    algorithm = SSI(
        name="ssicov",
        method="cov",
        br=window["block_rows"],
        ordmax=window["max_order"],
        calc_unc=True,
        nb=window["blocks"],
    )
    setup.add_algorithms(algorithm)
    setup.run_by_name("ssicov")
    r = algorithm.result
    # pyOMA2's own stabilisation labels (Lab == 1: stable in frequency, damping and shape
    # under its default soft and hard criteria). Its `mpe(order_in="find_min")` wants every
    # mode stable at one order, within an absolute tolerance in Hz; per mode instead, the
    # stable poles within 0.5 % of the frequency asked for, and of those the one at the
    # median order of the mode's stable column.
    fn, lab = np.asarray(r.Fn_poles), np.asarray(r.Lab)
    modes = []
    for f in window["frequencies_hz"]:
        rows, cols = np.where((lab == 1) & (np.abs(fn - f) <= 0.005 * f))
        if len(cols) == 0:
            modes.append(None)
            continue
        by_order = sorted(zip(cols, rows))
        col, row = by_order[len(by_order) // 2]
        phi = np.asarray(r.Phi_poles[row, col, :])
        # Normalised like Triax's shapes: the largest component is 1.
        reference = int(np.argmax(np.abs(phi)))
        phi = phi / phi[reference]
        modes.append({
            "frequency_hz": float(fn[row, col]),
            "frequency_std_hz": float(r.Fn_poles_std[row, col]),
            "damping_ratio": float(r.Xi_poles[row, col]),
            "damping_std": float(r.Xi_poles_std[row, col]),
            "order": int(col * 1),
            "stable_orders": int(len(set(cols))),
            "shape_real": [float(v) for v in phi.real],
            "shape_imag": [float(v) for v in phi.imag],
        })
    return modes


def main():
    directory = sys.argv[1]
    with open(os.path.join(directory, "windows.json")) as f:
        windows = json.load(f)["windows"]
    out = {"pyoma2": __import__("importlib.metadata").metadata.version("pyOMA-2"),
           "windows": [identify(w, directory) for w in windows]}
    with open(os.path.join(directory, "pyoma2.json"), "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main()
