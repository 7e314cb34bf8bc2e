"""`fae export` in a real browser: three.js's GLTFLoader opens the exported shipped head with
expressions.fap in headless Chromium (Debian's, driven by Playwright), and its animation,
set to two times, moves the face between the two pictures."""

from __future__ import annotations

import functools
import http.server
import threading
from pathlib import Path

import numpy as np
import pytest

from test_live_view import browser_problem, launch_chromium

REPO = Path(__file__).resolve().parents[1]

PAGE = """<!doctype html><html><head><meta charset="utf-8">
<script type="importmap">
{ "imports": { "three": "/three/build/three.module.js", "three/addons/": "/three/examples/jsm/" } }
</script></head><body style="margin:0">
<script type="module">
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
const renderer = new THREE.WebGLRenderer({ preserveDrawingBuffer: true });
renderer.setSize(400, 400);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0xc8ccd4);
scene.add(new THREE.HemisphereLight(0xffffff, 0x404048, 2.0));
const light = new THREE.DirectionalLight(0xffffff, 1.5);
light.position.set(0.3, 0.5, 1.0);
scene.add(light);
const camera = new THREE.PerspectiveCamera(30, 1, 0.01, 10);
new GLTFLoader().load("/scene.glb", (gltf) => {
  scene.add(gltf.scene);
  const box = new THREE.Box3().setFromObject(gltf.scene);
  const c = box.getCenter(new THREE.Vector3()), size = box.getSize(new THREE.Vector3());
  const face = new THREE.Vector3(c.x, c.y + 0.2 * size.y, c.z);  // the face, above the neck
  camera.position.set(face.x, face.y, face.z + 1.6 * size.y);
  camera.lookAt(face);
  const mixer = new THREE.AnimationMixer(gltf.scene);
  for (const clip of gltf.animations) mixer.clipAction(clip).play();
  window.show = (t) => { mixer.setTime(t); renderer.render(scene, camera); return true; };
  let targets = 0;
  gltf.scene.traverse((o) => { if (o.morphTargetInfluences) targets += o.morphTargetInfluences.length; });
  window.loaded = { animations: gltf.animations.length, duration: gltf.animations.length ? gltf.animations[0].duration : 0,
                    morphTargets: targets };
}, undefined, (e) => { window.loadError = String(e); });
</script></body></html>
"""


class _Files(http.server.SimpleHTTPRequestHandler):
    """The test page and the exported scene from one folder, three.js's files from npm."""

    def __init__(self, *args, folder: Path, three: Path, **kwargs):
        self.three = three
        super().__init__(*args, directory=str(folder), **kwargs)

    def translate_path(self, path):
        path = path.split("?", 1)[0]
        if path.startswith("/three/"):
            return str(self.three / path[len("/three/"):])
        return super().translate_path(path)

    def log_message(self, *args):
        pass


@pytest.mark.slow
@pytest.mark.skipif(browser_problem() is not None, reason=str(browser_problem()))
def test_three_js_plays_the_exported_expressions(tmp_path):
    from playwright.sync_api import sync_playwright

    from fae.animate.bake import baked_model, bake_tables
    from fae.animate.player import Player, playable_head
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel, write_facemodel
    from fae.net.view import find_three
    from test_export_gltf import run_command

    physics = Player(playable_head(read_facemodel(shipped_head_path())))
    head = tmp_path / "baked.glb"
    write_facemodel(baked_model(physics.face, bake_tables(physics, (3, 12, 13, 31, 32), intervals_per_side=2)), head)
    assert run_command("export", [str(head), str(REPO / "fap_streams" / "expressions.fap"),
                                  "-o", str(tmp_path / "scene.glb")]) == 0
    (tmp_path / "index.html").write_text(PAGE)
    handler = functools.partial(_Files, folder=tmp_path, three=find_three())
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport={"width": 400, "height": 400})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
            page.wait_for_function("window.loaded || window.loadError", timeout=120000)
            loaded = page.evaluate("window.loaded || window.loadError")
            shots = {}
            for t in (0.0, loaded["duration"] / 12):  # neutral, then joy at its height (6 expressions)
                page.evaluate(f"window.show({t})")
                shots[t] = tmp_path / f"t{t:.2f}.png"
                page.screenshot(path=str(shots[t]))
            browser.close()
    finally:
        server.shutdown()
    assert errors == []
    assert loaded["animations"] == 1 and loaded["duration"] > 1.0 and loaded["morphTargets"] > 0
    from PIL import Image

    a, b = (np.asarray(Image.open(s).convert("RGB"), dtype=float) for s in shots.values())
    assert a.std() > 10  # the head is drawn, not an empty canvas
    assert np.abs(a - b).mean() > 0.3  # the face moved between the two times
