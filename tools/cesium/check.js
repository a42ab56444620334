// window.tilesetCheck: {done, error, errors, failed, loaded, features, ids, seconds}
// and window.tilesetCheck.pickAt(x, y, z): the "id" of the feature under the screen
// centre once the camera looks straight down at the EPSG:4978 point (x, y, z).
"use strict";

const check = { done: false, error: null, errors: [], failed: [], loaded: [], features: 0, ids: [], seconds: null };
window.tilesetCheck = check;
window.addEventListener("error", (e) => check.errors.push(String(e.message)));
window.addEventListener("unhandledrejection", (e) => check.errors.push(String(e.reason)));

const params = new URLSearchParams(location.search);
const timeoutMs = Number(params.get("timeout") || 60000);
Cesium.Ion.defaultAccessToken = "";

const widget = new Cesium.CesiumWidget("view", {
  baseLayer: false,
  terrainProvider: new Cesium.EllipsoidTerrainProvider(),
  skyBox: false,
  skyAtmosphere: false,
  requestRenderMode: false,
});
const scene = widget.scene;
scene.renderError.addEventListener((_, e) => check.errors.push(`render error: ${e}`));

function frames(n) {
  return new Promise((resolve) => {
    const listener = () => { if (--n <= 0) { scene.postRender.removeEventListener(listener); resolve(); } };
    scene.postRender.addEventListener(listener);
  });
}

function contents(tile, out) {
  if (tile.content && tile.content.featuresLength !== undefined && tile.contentReady) out.push(tile.content);
  tile.children.forEach((child) => contents(child, out));
  return out;
}

function untilAllLoaded(tileset) {
  return new Promise((resolve, reject) => {
    const timer = setTimeout(() => reject(new Error(`allTilesLoaded not raised in ${timeoutMs} ms`)), timeoutMs);
    const listener = () => { clearTimeout(timer); tileset.allTilesLoaded.removeEventListener(listener); resolve(); };
    tileset.allTilesLoaded.addEventListener(listener);
  });
}

async function main() {
  const start = performance.now();
  const tileset = await Cesium.Cesium3DTileset.fromUrl(params.get("tileset"));
  tileset.tileFailed.addEventListener((e) => check.failed.push({ url: e.url, message: String(e.message) }));
  tileset.tileLoad.addEventListener((tile) => check.loaded.push(tile.content.url));
  const loaded = untilAllLoaded(tileset);
  scene.primitives.add(tileset);
  const sphere = tileset.boundingSphere;
  widget.camera.flyToBoundingSphere(sphere, {
    duration: 0, offset: new Cesium.HeadingPitchRange(0.0, -0.6, 3.0 * sphere.radius),
  });
  await loaded;
  check.seconds = (performance.now() - start) / 1000;
  const all = contents(tileset.root, []);
  check.features = all.reduce((sum, c) => sum + c.featuresLength, 0);
  check.ids = all.flatMap((c) => Array.from({ length: c.featuresLength }, (_, k) => c.getFeature(k).getProperty("id")));

  check.pickAt = async (x, y, z) => {
    const target = new Cesium.Cartesian3(x, y, z);
    widget.camera.lookAt(target, new Cesium.HeadingPitchRange(0.0, -Cesium.Math.PI_OVER_TWO, 60.0));
    await frames(3);
    const centre = new Cesium.Cartesian2(scene.canvas.clientWidth / 2, scene.canvas.clientHeight / 2);
    const picked = scene.pick(centre);
    widget.camera.lookAtTransform(Cesium.Matrix4.IDENTITY);
    return picked instanceof Cesium.Cesium3DTileFeature ? picked.getProperty("id") : null;
  };
}

main().catch((e) => { check.error = String(e && e.stack || e); }).finally(() => { check.done = true; });
