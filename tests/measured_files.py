"""Mitsuba ``measured`` files (RGL-EPFL ``tensor_file``) made by the tests.

The files have the layout of the RGL-EPFL measurements (one incident azimuth, 8 incident
elevations, a 32x32 grid of the half-vector parameterization, RGB) and a flat microfacet
distribution, so that the sampling warp is the identity and the grid holds the BRDF itself as a
function of the half vector: ``(kd + ks * exp(-tan^2(theta_h) / alpha^2)) cos(theta_o)``, a
diffuse base and a Beckmann-shaped lobe (the cosine is part of the stored values). Mitsuba's own ``measured`` plugin reads, evaluates
and samples them as it does a real measurement; no measured data is copied.
"""

import struct

import numpy as np

#: Float32 and UInt8/UInt32 codes of Mitsuba's ``tensor_file`` fields.
_FLOAT32, _UINT8, _UINT32 = 10, 1, 5
#: Incident elevations of the RGL-EPFL files (radians).
THETA_I = np.array([0.0, 0.485, 0.698, 0.874, 1.037, 1.198, 1.369, np.pi / 2], np.float32)
#: Materials of the tests: name -> (description, kd RGB, ks RGB, alpha).
MATERIALS = {
    "paper_blue": ("blue paper, nearly diffuse", (0.10, 0.18, 0.45), (0.02, 0.02, 0.02), 0.5),
    "ilm_l3_37_metallic": ("a metallic paint", (0.05, 0.04, 0.03), (0.9, 0.7, 0.45), 0.25),
    "vch_golden_yellow": ("a glossy yellow film", (0.55, 0.38, 0.05), (0.6, 0.6, 0.6), 0.12),
}
#: File name of each material, as the RGL-EPFL database names them.
JACOBIAN = 0
FILES = {name: name + "_rgb.bsdf" for name in MATERIALS}


def _grid(kd, ks, alpha, n=32):
    """The stored values (n_theta_i, 3, n, n): the BRDF times ``cos(theta_o)`` (the cosine is in
    the data of these files) on the grid of the half vector, whose x is ``sqrt(2 theta_h / pi)``
    and y the azimuth ``phi_h - phi_i`` mapped from ``[-pi, pi]`` to ``[0, 1]``."""
    u = np.linspace(0.0, 1.0, n)
    theta_h = np.minimum(u * u * np.pi / 2, np.pi / 2 - 1e-3)[None, :]
    phi_h = (np.linspace(0.0, 1.0, n) * 2 * np.pi - np.pi)[:, None]
    lobe = np.exp(-(np.tan(theta_h) ** 2) / alpha**2)  # (1, n)
    f = np.asarray(kd)[:, None, None] + np.asarray(ks)[:, None, None] * lobe[None]  # (3, 1, n)
    h = np.stack(
        np.broadcast_arrays(
            np.sin(theta_h) * np.cos(phi_h), np.sin(theta_h) * np.sin(phi_h), np.cos(theta_h)
        )
    )  # (3, n, n)
    out = []
    for t in THETA_I:
        wi = np.array([np.sin(t), 0.0, np.cos(t)])
        d = np.tensordot(wi, h, 1)
        cos_o = np.clip(2 * d * h[2] - wi[2], 0.0, None) * (d > 0)
        out.append(f * cos_o[None])
    return np.array(out, np.float32)


def write_measured(path, description, kd, ks, alpha, n_theta=len(THETA_I)):
    """Write a ``tensor_file`` Mitsuba's ``measured`` plugin reads; returns ``path``."""
    rgb = _grid(kd, ks, alpha)[:n_theta]
    lum = 0.2126 * rgb[:, 0] + 0.7152 * rgb[:, 1] + 0.0722 * rgb[:, 2]
    fields = [
        ("version", _UINT32, np.array([1, 0], np.uint32)),
        ("description", _UINT8, np.frombuffer(description.encode(), np.uint8)),
        ("phi_i", _FLOAT32, np.zeros(1, np.float32)),
        ("theta_i", _FLOAT32, THETA_I[:n_theta]),
        ("sigma", _FLOAT32, np.ones((2, 128), np.float32)),
        ("ndf", _FLOAT32, np.full((2, 128), 4.0, np.float32)),  # ndf / (4 sigma) = 1
        ("vndf", _FLOAT32, np.full((1, n_theta, 128, 128), 1.0 / 128**2, np.float32)),
        ("luminance", _FLOAT32, lum[None]),
        ("rgb", _FLOAT32, rgb[None]),
        ("jacobian", _UINT8, np.array([JACOBIAN], np.uint8)),
        ("valid", _UINT8, np.full(1024, 255, np.uint8)),
    ]
    head = b"tensor_file\0" + bytes([1, 0]) + struct.pack("<I", len(fields))
    for name, code, a in fields:
        head += struct.pack("<H", len(name)) + name.encode() + struct.pack("<HBQ", a.ndim, code, 0)
        head += struct.pack("<" + "Q" * a.ndim, *a.shape)
    body, offsets = b"", []
    start = len(head)
    for _, _, a in fields:
        pad = -(start + len(body)) % 8
        body += bytes(pad)
        offsets.append(start + len(body))
        body += np.ascontiguousarray(a).tobytes()
    # the offsets, written in place of the zeros above
    out = bytearray(head)
    pos = 18
    for (name, _, a), off in zip(fields, offsets):
        pos += 2 + len(name) + 3
        struct.pack_into("<Q", out, pos, off)
        pos += 8 + 8 * a.ndim
    with open(path, "wb") as f:
        f.write(bytes(out) + body)
    return path


def write_all(folder):
    """The three test materials in ``folder`` (created); returns ``{name: path}``."""
    import os

    os.makedirs(folder, exist_ok=True)
    return {
        name: write_measured(os.path.join(folder, FILES[name]), *MATERIALS[name])
        for name in MATERIALS
    }
