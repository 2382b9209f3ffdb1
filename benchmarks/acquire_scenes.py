"""The scenes of ``tools/bench.py acquire``: the photo scene (the shipped sphere under the sky map
and a point light, the issue's set-up) and the judging scene (another camera, the sky map turned
and dimmed, a point light and a spherical area light elsewhere), each with the BSDF on the sphere
given as XML (a ``manifold_brdf`` or Mitsuba's ``measured``).
"""

import os

from mitsuba_manifold.render.scene.scenes import scene_path

PHOTO_CAMERA = "0, 0.6, 5"
JUDGE_CAMERA = "3.4, 2.4, 2.6"

_TEMPLATE = """<?xml version="1.0" encoding="utf-8"?>
<scene version="3.0.0">
    <default name="manifold" value="{manifold}"/>
    <default name="x" value=""/>
    <default name="spp" value="64"/>
    <default name="res" value="64"/>
    <integrator type="path"><integer name="max_depth" value="8"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="32"/>
        <transform name="to_world"><lookat origin="{camera}" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="$res"/><integer name="height" value="$res"/>
            <string name="pixel_format" value="rgb"/><rfilter type="box"/>
        </film>
    </sensor>
    {bsdf}
    <shape type="sphere" id="object">
        <point name="center" value="0, 0, 0"/><float name="radius" value="1"/>
        <ref id="material"/>
    </shape>
    {lights}
</scene>
"""

PHOTO_LIGHTS = """<emitter type="envmap" id="sky"><string name="filename" value="{sky}"/></emitter>
    <emitter type="point" id="lamp">
        <point name="position" value="-3, 4, 3"/><rgb name="intensity" value="20, 20, 20"/>
    </emitter>"""

JUDGE_LIGHTS = """<emitter type="envmap" id="sky">
        <string name="filename" value="{sky}"/><float name="scale" value="0.7"/>
        <transform name="to_world"><rotate y="1" angle="140"/><rotate x="1" angle="12"/></transform>
    </emitter>
    <emitter type="point" id="lamp">
        <point name="position" value="4.5, 1.0, -1.5"/><rgb name="intensity" value="30, 26, 22"/>
    </emitter>
    <shape type="sphere" id="softbox">
        <point name="center" value="-1.5, 3.5, 3.0"/><float name="radius" value="0.4"/>
        <emitter type="area"><rgb name="radiance" value="3, 3, 3.4"/></emitter>
    </shape>"""

MANIFOLD_BSDF = """<bsdf type="manifold_brdf" id="material">
        <string name="manifold" value="$manifold"/><string name="x" value="$x"/>
    </bsdf>"""


def measured_bsdf(path: str) -> str:
    """The XML of Mitsuba's ``measured`` BSDF reading ``path``."""
    return (
        '<bsdf type="measured" id="material">'
        f'<string name="filename" value="{os.path.abspath(path)}"/></bsdf>'
    )


def write_scene(path: str, kind: str, bsdf: str = MANIFOLD_BSDF, manifold: str = "") -> str:
    """Write the ``kind`` ("photo" or "judge") scene with ``bsdf`` on the sphere to ``path``."""
    sky = os.path.join(os.path.dirname(scene_path("sphere")), "sky.exr")
    camera, lights = (
        (PHOTO_CAMERA, PHOTO_LIGHTS) if kind == "photo" else (JUDGE_CAMERA, JUDGE_LIGHTS)
    )
    text = _TEMPLATE.format(
        manifold=manifold, camera=camera, bsdf=bsdf, lights=lights.format(sky=sky)
    )
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        f.write(text)
    return path
