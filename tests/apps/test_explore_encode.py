"""tools/explore.py without rendering: frame tonemapping and encoding, the latent map."""

import os

import numpy as np
import pytest

from mitsuba_manifold.apps.explore import encode, latentmap
from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.manifold.model import Manifold


@pytest.mark.parametrize("exposure", [0.0, 1.0, -3.0])
def test_fast_tonemap_equals_imageio(exposure):
    rng = np.random.default_rng(3)
    img = rng.lognormal(-2, 2.5, (40, 50, 3)).astype(np.float32)
    img[0, 0] = [np.nan, -1.0, np.inf]
    img[0, 1] = [-np.inf, np.nan, 0.5]
    thr = encode._THRESHOLDS[:-1]
    edges = np.concatenate(
        [thr, np.nextafter(thr, np.float32(0)), np.nextafter(thr, np.float32(2))]
    )
    edges = (edges / np.float32(2.0**exposure)).astype(np.float32)
    for a in (img, np.repeat(edges[None, :, None], 3, axis=2)):
        np.testing.assert_array_equal(encode.tonemap(a, exposure), imageio.tonemap(a, exposure))


def test_fractional_exposure_within_one_level():
    img = np.random.default_rng(4).lognormal(-2, 2, (64, 64, 3)).astype(np.float32)
    d = encode.tonemap(img, 0.37).astype(int) - imageio.tonemap(img, 0.37)
    assert np.abs(d).max() <= 1 and (d != 0).mean() < 1e-3


@pytest.mark.parametrize("fmt", ["rgba", "png", "jpeg"])
def test_encodings_decode_to_the_frame(fmt):
    import io

    from PIL import Image

    yy, xx = np.mgrid[:32, :48]
    rgb = np.stack([4 * xx, 6 * yy, 255 - 3 * xx], axis=-1).astype(
        np.uint8
    )  # smooth, as renders are
    data = encode.encode(rgb, fmt)
    if fmt == "rgba":
        out = np.frombuffer(data, np.uint8).reshape(32, 48, 4)
        assert (out[..., 3] == 255).all()
        np.testing.assert_array_equal(out[..., :3], rgb)
        return
    out = np.asarray(Image.open(io.BytesIO(data)).convert("RGB")).astype(int)
    if fmt == "png":
        np.testing.assert_array_equal(out, rgb)
    else:
        assert np.abs(out - rgb).mean() < 2.0


def test_latent_map_slices_through_the_point(small_db, tmp_path):
    m = Manifold.fit(small_db, q=3, max_iter=30)
    a = latentmap.render(m, m.latent[0], dims=(0, 2), resolution=48)
    b = latentmap.render(m, m.latent[5], dims=(0, 2), resolution=48)
    assert a.image.shape == (48, 48, 4) and a.dims == (0, 2)
    assert not np.array_equal(a.image, b.image)  # the third coordinate follows the point
    assert a.albedo_range == b.albedo_range  # one colour scale for every slice
    assert a.albedo_range[1] >= m.albedos.mean(axis=-1).max()
    lo, hi = a.extent[0], a.extent[1]
    assert lo < m.latent[:, 0].min() and hi > m.latent[:, 0].max()


# ------------------------------------------------------ listening address


@pytest.mark.parametrize("port", ["99999", "65536", "-1", "http"])
def test_cli_refuses_a_port_out_of_range_when_parsing(port, tmp_path, capsys):
    from mitsuba_manifold.apps.cli.explore import main

    with pytest.raises(SystemExit) as e:  # refused before any basis is read
        main(["--basis", str(tmp_path / "nothing"), "--port", port])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1
    assert f"--port: must be an integer in 0..65535 (0: any free port), got '{port}'" in err


@pytest.mark.parametrize(
    "host", ["999.1.1.1", "192.0.2.1"]
)  # no such address; not this machine's (TEST-NET-1)
def test_a_bad_host_names_host_not_port(host):
    from mitsuba_manifold.apps.cli.explore import bind

    with pytest.raises(OSError, match=f"--host {host} is not an address of this machine") as e:
        bind(host, 0)
    assert "--port" not in str(e.value)


def test_a_busy_port_names_port_not_host():
    from mitsuba_manifold.apps.cli.explore import bind

    sock = bind("127.0.0.1", 0)
    try:
        port = sock.getsockname()[1]
        with pytest.raises(
            OSError, match=f"--port {port} is not free to use .*choose another --port"
        ) as e:
            bind("127.0.0.1", port)
        assert "--host" not in str(e.value)
    finally:
        sock.close()


@pytest.mark.parametrize("cores, threads", [(None, None), (1, 1), (2, 1), (3, 1), (4, 2), (16, 14)])
def test_the_server_leaves_two_cores_to_the_browser_and_the_frames(cores, threads):
    from mitsuba_manifold.apps.cli.explore import server_blas_threads

    got = server_blas_threads(cores)
    assert got == threads if threads else 1 <= got <= max(1, (os.cpu_count() or 1) - 2)
