"""Small measured databases for tests: NBRDF networks tabulated at a low resolution."""

import os

from mitsuba_manifold.data import merl, nbrdf

#: The NBRDF weights the package ships.
WEIGHTS = nbrdf.WEIGHTS_PATH
#: Resolution of the test tables (n_theta_h, n_theta_d, n_phi_d).
DIMS = (12, 12, 24)
#: MERL materials of the test manifolds (diffuse, glossy, metals, paints).
MERL = (
    "alum-bronze",
    "black-oxidized-steel",
    "blue-metallic-paint",
    "blue-rubber",
    "chrome",
    "dark-blue-paint",
    "gold-metallic-paint",
    "green-plastic",
    "pearl-paint",
    "red-fabric",
    "silver-paint",
    "teflon",
    "white-paint",
    "yellow-matte-plastic",
    "color-changing-paint3",
    "polyethylene",
    "white-fabric",
    "black-phenolic",
)


def weights_path():
    """The NBRDF weights file the package ships."""
    return os.path.abspath(WEIGHTS)


def write_set(folder, prefix, names=None, dims=DIMS):
    """Write the networks ``names`` (default all) of set ``prefix`` as ``.binary`` tables in ``folder``."""
    nets = nbrdf.NetworkSet.load(weights_path(), prefix)
    os.makedirs(folder, exist_ok=True)
    for name in names or nets.names:
        merl.write_binary(
            os.path.join(folder, name + ".binary"), merl.to_stored(nbrdf.tabulate(nets, name, dims))
        )
    return folder
