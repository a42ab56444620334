// The recon3d run viewer: buildings.glb (one node per building, its attributes in the
// node's extras) on the run's ground, coloured by LoD or by quality, or shown as the
// images saw it (buildings_textured.glb, stereo runs); a click shows a building's
// attributes. Everything is in the GLB's local frame (Y up, north is -Z).
// Test hook: window.recon3dViewer.
import {
  Box3, Color, DirectionalLight, DoubleSide, GLTFLoader, HemisphereLight, Mesh, MeshBasicMaterial,
  MeshLambertMaterial, OrbitControls, PerspectiveCamera, PlaneGeometry, Raycaster,
  SRGBColorSpace, Scene, TextureLoader, Vector2, Vector3, WebGLRenderer,
} from "./three.min.js";

const LOD_COLOURS = { "1": "#7fa8d1", "1.2": "#8fc1a9", "1.3": "#f0b45b", "2.2": "#d98a6c" };
const NO_VALUE = "#9e9e9e";
const NOT_OK = "#9c5fc9";
const RMS_RED = 2.0; // metres of roof RMS drawn fully red, the scale of report.html's map
const RAMP = ["#2ca25f", "#f0c419", "#d7301f"].map((c) => new Color(c)); // 0, RMS_RED / 2, RMS_RED
const SELECTED = "#00c8ff";

const $ = (id) => document.getElementById(id);
const canvas = $("view");
const renderer = new WebGLRenderer({ canvas, antialias: true });
renderer.setPixelRatio(window.devicePixelRatio);
const scene = new Scene();
scene.background = new Color("#dfe5ea");
const camera = new PerspectiveCamera(40, 1, 1, 1e5);
const controls = new OrbitControls(camera, canvas);
const render = () => renderer.render(scene, camera);
controls.addEventListener("change", render);

// The sun of the hillshade: from the north-west, 45 degrees high.
scene.add(new HemisphereLight("#ffffff", "#7a7264", 1.5));
const sun = new DirectionalLight("#ffffff", 1.8);
sun.position.set(-0.5, Math.SQRT1_2, -0.5);
scene.add(sun);

let mode = "lod";
let selected = null;
const byId = new Map();
let photo = null; // the textured model, when the run has one

// The buildings textured from the images; hidden until the "photo" mode shows it.
async function loadPhoto() {
  const gltf = await new GLTFLoader().loadAsync("run/buildings_textured.glb");
  gltf.scene.visible = false;
  scene.add(gltf.scene);
  return gltf.scene;
}

async function loadBuildings() {
  const gltf = await new GLTFLoader().loadAsync("run/buildings.glb");
  gltf.scene.traverse((object) => {
    if (object.isMesh && object.userData.id !== undefined) {
      // Surfaces read from another tool (MultiSurface) may not close: show their backs too.
      const side = object.userData.geometry_type === "MultiSurface" ? DoubleSide : undefined;
      object.material = new MeshLambertMaterial({ flatShading: true, side });
      byId.set(String(object.userData.id), object);
    }
  });
  scene.add(gltf.scene);
  return gltf.scene;
}

// The DTM as a grid of heights, draped with the hillshade (or orthophoto) texture.
async function loadGround(ground) {
  const [west, south, east, north] = ground.extent;
  const { rows, cols, z } = ground.heights;
  const geometry = new PlaneGeometry(east - west, north - south, cols - 1, rows - 1);
  const position = geometry.attributes.position; // row-major from the north-west corner, like z
  z.forEach((height, i) => position.setZ(i, height));
  geometry.rotateX(-Math.PI / 2); // the plane's +Y (north) becomes -Z, its Z the height (Y)
  geometry.translate((west + east) / 2, 0, -(south + north) / 2);
  const texture = await new TextureLoader().loadAsync("run/ground.png");
  texture.colorSpace = SRGBColorSpace;
  texture.anisotropy = renderer.capabilities.getMaxAnisotropy();
  // Pushed back in depth so building footprints never flicker through it.
  const material = new MeshBasicMaterial({ map: texture, polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 4 });
  const mesh = new Mesh(geometry, material);
  scene.add(mesh);
  return mesh;
}

function colourOf(data) {
  if (mode === "lod" || mode === "photo") return LOD_COLOURS[data.lod] ?? NO_VALUE;
  if (data.status !== undefined && data.status !== "ok") return NOT_OK;
  if (typeof data.roof_rms_m !== "number") return NO_VALUE;
  const t = Math.min(Math.max(data.roof_rms_m / RMS_RED, 0), 1);
  return `#${RAMP[0].clone().lerp(RAMP[1], Math.min(2 * t, 1)).lerp(RAMP[2], Math.max(2 * t - 1, 0)).getHexString()}`;
}

function legendEntries() {
  const all = [...byId.values()].map((m) => m.userData);
  const count = (test) => all.filter(test).length;
  if (mode === "photo") return [[SELECTED, "selected building"]];
  if (mode === "lod") {
    const lods = [...new Set(all.map((d) => d.lod))].sort();
    return lods.map((lod) => [LOD_COLOURS[lod] ?? NO_VALUE, `LoD ${lod}: ${count((d) => d.lod === lod)}`]);
  }
  const ramp = [0, 0.5, 1, 1.5, 2].map((rms) => [colourOf({ roof_rms_m: rms }), `roof RMS ${rms}${rms === 2 ? "+" : ""} m`]);
  return [...ramp, [NOT_OK, `status not ok (fallback): ${count((d) => d.status !== undefined && d.status !== "ok")}`],
    [NO_VALUE, "no roof RMS"]];
}

// In the photo mode the coloured meshes stay for picking, drawn only for the selected
// building, as a see-through highlight over its textures.
function showColoured(id, mesh) {
  const shown = mode !== "photo" || id === selected;
  mesh.material.visible = shown;
  mesh.material.transparent = mode === "photo";
  mesh.material.opacity = mode === "photo" ? 0.5 : 1;
  mesh.material.polygonOffset = mode === "photo"; // drawn over the textured faces it lies on
  mesh.material.polygonOffsetFactor = -1;
  mesh.material.polygonOffsetUnits = -4;
  mesh.material.color.set(id === selected ? SELECTED : colourOf(mesh.userData));
}

function setMode(next) {
  mode = next;
  for (const name of ["lod", "quality", "photo"]) $(`by-${name}`).setAttribute("aria-pressed", String(mode === name));
  if (photo) photo.visible = mode === "photo";
  for (const [id, mesh] of byId) showColoured(id, mesh);
  $("legend").innerHTML = legendEntries().map(([c, text]) => `<div><span style="background:${c}"></span>${text}</div>`).join("");
  render();
}

const escape = (text) => String(text).replace(/[&<>"]/g, (c) => `&#${c.charCodeAt(0)};`);
const format = (value) => (typeof value === "number" && !Number.isInteger(value) ? value.toFixed(3) : JSON.stringify(value).replace(/^"|"$/g, ""));

function select(id) {
  const previous = selected;
  selected = id;
  if (previous) showColoured(previous, byId.get(previous));
  if (id === null) {
    $("building").textContent = "Click a building to see its attributes.";
  } else {
    const mesh = byId.get(id);
    showColoured(id, mesh);
    const rows = Object.entries(mesh.userData).filter(([key]) => key !== "surface_types" && key !== "name");
    $("building").innerHTML = `<table>${rows.map(([k, v]) => `<tr><td>${escape(k)}</td><td>${escape(format(v))}</td></tr>`).join("")}</table>`;
  }
  render();
}

// A click (not a drag) picks the nearest building under the pointer; the ground hides what it covers.
function pickAt(event, ground) {
  const rect = canvas.getBoundingClientRect();
  const ndc = new Vector2(((event.clientX - rect.left) / rect.width) * 2 - 1, -((event.clientY - rect.top) / rect.height) * 2 + 1);
  const raycaster = new Raycaster();
  raycaster.setFromCamera(ndc, camera);
  const hit = raycaster.intersectObjects([...byId.values(), ...(ground ? [ground] : [])], false)[0];
  select(hit && hit.object !== ground ? String(hit.object.userData.id) : null);
}

// The centre of the building's largest roof triangle, a point on its surface, in window pixels.
function project(id) {
  const mesh = byId.get(id);
  const { index, attributes: { position } } = mesh.geometry;
  const [first, count] = mesh.userData.surface_types?.RoofSurface ?? [0, index.count / 3];
  const a = new Vector3(), b = new Vector3(), c = new Vector3();
  let best = null, bestArea = -1;
  for (let t = first; t < first + count; t++) {
    a.fromBufferAttribute(position, index.getX(3 * t));
    b.fromBufferAttribute(position, index.getX(3 * t + 1));
    c.fromBufferAttribute(position, index.getX(3 * t + 2));
    const area = new Vector3().crossVectors(b.clone().sub(a), c.clone().sub(a)).length();
    if (area > bestArea) {
      bestArea = area;
      best = a.clone().add(b).add(c).divideScalar(3);
    }
  }
  const ndc = mesh.localToWorld(best).project(camera);
  const rect = canvas.getBoundingClientRect();
  return { x: rect.left + ((ndc.x + 1) / 2) * rect.width, y: rect.top + ((1 - ndc.y) / 2) * rect.height };
}

const boxCorners = (box) => [0, 1, 2, 3, 4, 5, 6, 7].map((i) => new Vector3(
  i & 1 ? box.max.x : box.min.x, i & 2 ? box.max.y : box.min.y, i & 4 ? box.max.z : box.min.z));

// Horizontal direction from the centre to the camera: across the points' longest extent
// (a strip of city then fills the wide view), from the south; south-west for a compact site.
function viewAzimuth(points, centre) {
  let xx = 0, zz = 0, xz = 0;
  for (const p of points) {
    const dx = p.x - centre.x, dz = p.z - centre.z;
    [xx, zz, xz] = [xx + dx * dx, zz + dz * dz, xz + dx * dz];
  }
  const spread = Math.hypot(xx - zz, 2 * xz) / (xx + zz + 1e-9); // 0 round, 1 a line
  if (spread < 0.3) return new Vector3(-0.6, 0, 0.8);
  const major = 0.5 * Math.atan2(2 * xz, xx - zz);
  const across = new Vector3(-Math.sin(major), 0, Math.cos(major));
  return across.z < 0 ? across.negate() : across;
}

// Look at the objects from about 56 degrees above the horizon, moved in or out until
// the corners of their boxes just fill the view.
function frameView(objects) {
  const boxes = objects.map((o) => new Box3().setFromObject(o));
  const centre = boxes.reduce((all, box) => all.union(box), new Box3()).getCenter(new Vector3());
  const corners = boxes.flatMap(boxCorners);
  const direction = viewAzimuth(corners, centre).multiplyScalar(0.55).add(new Vector3(0, 0.83, 0)).normalize();
  let distance = Math.max(...corners.map((c) => c.distanceTo(centre)), 10);
  for (let pass = 0; pass < 4; pass++) {
    camera.position.copy(centre).addScaledVector(direction, distance);
    camera.lookAt(centre);
    camera.updateMatrixWorld();
    const reach = Math.max(...corners.map((c) => { const p = c.clone().project(camera); return Math.max(Math.abs(p.x), Math.abs(p.y)); }));
    distance *= reach / 0.9;
  }
  camera.near = distance / 200;
  camera.far = distance * 20;
  camera.updateProjectionMatrix();
  controls.target.copy(centre);
  controls.update();
}

function resize() {
  renderer.setSize(canvas.clientWidth, canvas.clientHeight, false);
  camera.aspect = canvas.clientWidth / canvas.clientHeight;
  camera.updateProjectionMatrix();
  render();
}

async function main() {
  const info = await (await fetch("run/scene.json")).json();
  $("title").textContent = info.title;
  const buildings = await loadBuildings();
  if (info.textured) {
    photo = await loadPhoto();
    $("by-photo").hidden = false;
  }
  const ground = info.ground ? await loadGround(info.ground) : null;
  resize();
  window.addEventListener("resize", resize);
  frameView(byId.size ? [...byId.values()] : [ground ?? buildings]);
  setMode("lod");
  $("by-lod").onclick = () => setMode("lod");
  $("by-quality").onclick = () => setMode("quality");
  $("by-photo").onclick = () => setMode("photo");
  let down = null;
  canvas.addEventListener("pointerdown", (e) => { down = [e.clientX, e.clientY]; });
  canvas.addEventListener("pointerup", (e) => {
    if (down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) < 4) pickAt(e, ground);
  });
  $("status").textContent = `${byId.size} buildings loaded; ground: ${info.ground ? info.ground.kind : "none"}; ${info.crs ?? ""}`;
  window.recon3dViewer = {
    ids: [...byId.keys()],
    mode: () => mode,
    setMode,
    colour: (id) => `#${byId.get(id).material.color.getHexString()}`,
    selected: () => selected,
    photo: () => ({ shown: Boolean(photo?.visible), buildings: photo ? photo.children.length : 0 }),
    project,
    ready: false,
  };
  requestAnimationFrame(() => { window.recon3dViewer.ready = true; });
}

main().catch((error) => {
  $("status").textContent = `error: ${error.message}`;
  window.recon3dViewer = { error: String(error) };
});
