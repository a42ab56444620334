// The parts of three.js the run viewer (recon3d/viewer/static/viewer.js) uses, bundled
// into one minified ES module by `npm run build-viewer --prefix tools`.
export {
  Box3, Color, DirectionalLight, DoubleSide, HemisphereLight, Mesh,
  MeshBasicMaterial, MeshLambertMaterial, PerspectiveCamera, PlaneGeometry, Raycaster,
  SRGBColorSpace, Scene, TextureLoader, Vector2, Vector3, WebGLRenderer,
} from "three";
export { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
export { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
