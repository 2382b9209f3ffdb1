"""Explore a material manifold in the browser: drag a latent point, see the material in the scene.

  explore.py --basis out/gi/basis_table_256_512_onepass [--basis OTHER ...] [--manifold M.npz]
             [--port 8765] [--host 127.0.0.1] [--allow-origin http://NAME:PORT ...]

Starts a local web server (127.0.0.1 unless --host says otherwise), prints the URL and
serves until Ctrl-C. It answers only requests addressed to 127.0.0.1, localhost or [::1]
with its port, or to --host (other Host headers are refused: DNS rebinding), and only pages
of those origins (http) or of an --allow-origin. Every image of every basis is read into memory first; the material
tables (for the WebGL preview, the negative-bin fraction and the BRDF slice) load in the
background while the page already works.

Acquire from a photo: the page's "Acquire from a photo" panel takes a photo of the basis's object
taken with its camera and lights (linear EXR, or PNG/JPEG in sRGB; another size of the same frame
is resized, up to 24 MiB as sent) and an optional mask, and shows the acquired material: the
basis's blend at its weights, its place on the latent map when a latent point explains the photo
as well (else the combination of measured materials by name, "beyond the manifold" where its
weights leave the simplex), the weights, the warnings (coverage, spread) and the contact sheet
photo | acquired | best single (docs/guides/acquisition.md). One acquisition runs at a time.

The server holds up against clients that misbehave: a connection whose request is not complete
within 5 s is closed (408), connections beyond 256 at once are refused (503), a page has at most
4 reference renders waiting or running (429 beyond), and a message repeated in the console is
shown once per 10 s with a count of the others.
"""

import argparse
import errno
import os
import socket
import sys

from ..tool_commands import explore_command

DEFAULT_PORT = 8765
#: This tool's command line for a basis (as the main job prints it).
command = explore_command


def parse_port(text):
    """A TCP port number 0..65535 (0: any free port)."""
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(
            f"must be an integer in 0..65535 (0: any free port), got {text!r}"
        )
    return port


def parser():
    from .common import ArgumentParser, add_prune_argument

    p = ArgumentParser(
        prog="explore.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--basis",
        action="append",
        required=True,
        metavar="DIR",
        help="basis folder (render_basis.py); repeat for several (a selector on the page)",
    )
    p.add_argument(
        "--manifold", help="manifold (.npz); default: the basis manifest's (checked by hash)"
    )
    p.add_argument(
        "--database",
        help="tables of the manifold: folder or built-in set name (default: the "
        "manifold's database)",
    )
    p.add_argument(
        "--scene",
        help="scene XML or shipped scene name for reference renders, checked against the "
        "basis (default: the manifest's scene, or the shipped one of that name)",
    )
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1: this machine only)",
    )
    p.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        metavar="ORIGIN",
        help="also answer requests for, and pages of, this origin (exactly: scheme, host, port, "
        "e.g. https://explore.example:443 behind a proxy); repeat for several",
    )
    p.add_argument(
        "--port",
        type=parse_port,
        default=DEFAULT_PORT,
        help=f"port (default {DEFAULT_PORT}; 0: any free port)",
    )
    add_prune_argument(p)
    p.add_argument(
        "--no-tables",
        action="store_true",
        help="do not load the material tables (no preview sphere, slice or negative-bin fraction)",
    )
    p.add_argument(
        "--refine-spp",
        type=int,
        default=16,
        help="where a drag ends, show the exact full-GI image: render the L2+ light at that point "
        "with this many samples per pixel (blend.py --refine; default 16, 0: never)",
    )
    p.add_argument(
        "--no-thumbnails",
        action="store_true",
        help="do not render the materials' thumbnails (made once in the background, cached beside the basis)",
    )
    return p


def bind(host, port):
    """A listening socket (so that port 0 picks a free port and the URL printed is exact)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        raise OSError(f"cannot listen on {host}:{port}: {_bind_problem(e, host, port)}") from None
    sock.listen(64)
    sock.set_inheritable(True)
    return sock


def _bind_problem(error, host, port):
    """Why binding failed and which option to change: --host when the address is the
    problem (unknown name, not this machine's), --port when the port is (in use, privileged).
    """
    reason = error.strerror or str(error)
    if isinstance(error, socket.gaierror) or error.errno == errno.EADDRNOTAVAIL:
        return (
            f"--host {host} is not an address of this machine ({reason}); choose another "
            "--host (127.0.0.1: this machine only, 0.0.0.0: every interface)"
        )
    if error.errno in (errno.EADDRINUSE, errno.EACCES):
        return (
            f"--port {port} is not free to use ({reason}); choose another --port (0: any free port)"
        )
    return f"{reason}; check --host {host} and --port {port}"


def url(sock):
    host, port = sock.getsockname()[:2]
    host = f"[{host}]" if ":" in host else host
    return f"http://{host}:{port}/"


def main(argv=None):
    args = parser().parse_args(argv)
    try:
        return serve(args)
    except KeyboardInterrupt:  # Ctrl-C before the server runs (while loading)
        print("explore: stopped", flush=True)
        return 130


def server_blas_threads(cores=None):
    """:func:`mitsuba_manifold.apps.explore.web.serving.server_blas_threads` (imported when called)."""
    from ..explore.web.serving import server_blas_threads as threads

    return threads(cores)


def serve(args):
    try:
        import uvicorn  # noqa: F401 (the explorer's extra)
    except ImportError:
        print(
            "error: the explorer needs its extra: pip install 'mitsuba-manifold[explore]'",
            file=sys.stderr,
        )
        return 2

    from ..explore import Explorer, create_app
    from ..explore.web.guard import MAX_MESSAGE, AllowList
    from ..explore.web.serving import make_server, quiet_logs
    from .common import ERRORS, cli_message

    try:
        sock = bind(args.host, args.port)
        allow = AllowList.for_server(
            args.host, sock.getsockname()[1], args.allow_origin, sock.getsockname()[0]
        )
    except ValueError as e:  # a bad --allow-origin
        sock.close()
        print(f"error: --allow-origin: {e}", file=sys.stderr)
        return 2
    except ERRORS as e:
        print(f"error: {cli_message(e)}", file=sys.stderr)
        return 2
    explorer = None
    try:
        from threadpoolctl import threadpool_limits

        from ..._util.blas import release_control

        # for the server's life, its BLAS products (maps, the path metric) leave two cores to
        # the page's browser and the frames: idle BLAS threads spin on the cores they wait for
        threadpool_limits(server_blas_threads(), user_api="blas")
        release_control()  # the frames' and paths' threads hold BLAS to one thread in turn
        print(f"loading {len(args.basis)} basis folder(s) ...", flush=True)
        explorer = Explorer(
            args.basis,
            manifold=args.manifold,
            database=args.database,
            prune=args.prune,
            load_tables=not args.no_tables,
            scene=args.scene,
            thumbnails=not args.no_thumbnails,
            refine_spp=args.refine_spp,
        )
        server = make_server(create_app(explorer, allow), MAX_MESSAGE)
        quiet_logs()
        for name, b in explorer.bases.items():
            print(
                f"basis {name}: {len(b.keys)} materials, {b.resolution[0]}x{b.resolution[1]}, {b.folder}"
            )
        print(
            f"manifold: {explorer.manifold_path} ({explorer.manifold.n} materials, q={explorer.manifold.q})"
        )
        if args.host not in ("127.0.0.1", "localhost", "::1"):
            print(
                f"warning: listening on {args.host}: other machines can reach this server",
                file=sys.stderr,
            )
        print(f"explore at {url(sock)}   (Ctrl-C stops)", flush=True)
        try:
            server.run(sockets=[sock])
        except KeyboardInterrupt:  # uvicorn stops gracefully, then passes the signal on
            pass
    except ERRORS as e:
        print(f"error: {cli_message(e)}", file=sys.stderr)
        return 2
    finally:
        if explorer is not None:
            explorer.close(wait=0.3)
        sock.close()
    print("explore: stopped", flush=True)
    # Exit without finalizing the interpreter: a render's pass, a frame being denoised in the
    # server's thread pool, the thumbnail sheet, the tables or the paths may still run in native
    # code, and finalizing under them can abort the process (a stopped server exited with -6 in CI).
    sys.stderr.flush()
    os._exit(0)


if __name__ == "__main__":
    sys.exit(main())
