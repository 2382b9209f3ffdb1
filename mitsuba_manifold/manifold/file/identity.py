"""The identity of a manifold: what it computes, not the bytes of its file.

Two manifolds with the same :func:`manifold_identity` hold the same materials at the same
latent points over the same tables, so per-material images rendered with one are valid for
the other. It does not include the interpolant (GP or Shepard weights and their settings):
the images of a basis do not depend on it, but weights do, so do not key anything that
depends on ``w(x)`` on this identity.
The identity hashes the material names, the tables' content hashes, the latent points
(float64 bytes), the kernel's length scale and noise and the fit's feature transform.
It leaves out everything that does not change the interpolant: fit timings, the
optimiser's history, the Gram matrix and albedos (both functions of the tables), the
database's folder (a moved database is the same database) and the file's own bytes
(``np.savez`` stores zip time stamps).
"""

import hashlib
import json

import numpy as np

#: Bumped when the definition changes (an old identity then never matches by accident).
IDENTITY_VERSION = 1


def manifold_identity(manifold):
    """SHA-256 (hex) of a :class:`Manifold`'s content (see the module docstring)."""
    latent = np.ascontiguousarray(manifold.latent, dtype="<f8")
    head = {
        "identity": IDENTITY_VERSION,
        "names": list(manifold.names),
        "hashes": list(manifold.hashes),
        "length_scale": float(manifold.length_scale).hex(),
        "noise": float(manifold.noise).hex(),
        "features": manifold.features,
        "shape": list(latent.shape),
    }
    h = hashlib.sha256(json.dumps(head, sort_keys=True).encode())
    h.update(latent.tobytes())
    return h.hexdigest()
