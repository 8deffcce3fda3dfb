"""The falling cat turns by a chosen angle at zero angular momentum (what `nhjax demo --holonomy` runs).

Usage: nhjax run falling_cat_somersault [--turn RAD] [--rtol TOL] [--out DIR]
"""

import argparse

import numpy as np

from nhjax.demos import somersault

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--turn", type=float, default=np.pi, help="turn of psi [rad], |turn| < 2 pi")
    ap.add_argument("--rtol", type=float, default=1e-10)
    ap.add_argument("--out", default="falling_cat_somersault", help="folder for the outputs (default: ./falling_cat_somersault)")
    a = ap.parse_args()
    somersault(out=a.out, rtol=a.rtol, atol=a.rtol, turn=a.turn)
