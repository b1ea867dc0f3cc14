// The 3D viewer: three.js with OrbitControls, z up (the object frame: origin on the turntable
// axis at the table top, +z up the axis, metres). Shows one model at a time as a mesh, a point
// cloud or voxels, over a 1 cm grid on the table plane with the turntable axis drawn in. Renders
// on demand (a change of view or model), never in a loop, so an idle page costs nothing.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { PLYLoader } from "three/addons/loaders/PLYLoader.js";

const BACKGROUND = 0x1d2127;
const MODEL_GREY = 0xc9ccd1;
const LIVE_COLOUR = 0x4fc3f7;

export class Viewer {
  /** `container`: the element the canvas fills. `onChange(info)`: called when the model changes. */
  constructor(container, onChange) {
    this.container = container;
    this.onChange = onChange || (() => {});
    this.wireframe = false;
    this.lighting = true;
    this.info = null;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    const canvas = this.renderer.domElement;
    canvas.id = "view";
    canvas.tabIndex = 0;
    canvas.setAttribute("role", "img");
    canvas.setAttribute("aria-label", "3D view. Drag to orbit, right-drag to pan, wheel to zoom; with focus, arrow keys orbit and + and - zoom.");
    container.appendChild(canvas);

    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(BACKGROUND);
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.001, 20);
    this.camera.up.set(0, 0, 1);
    this.camera.position.set(0.18, -0.32, 0.2);
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.target.set(0, 0, 0.04);
    this.controls.screenSpacePanning = true;
    this.controls.addEventListener("change", () => this.render());
    canvas.addEventListener("keydown", (e) => this.onKey(e));

    this.hemi = new THREE.HemisphereLight(0xffffff, 0x444444, 1.6);
    this.hemi.position.set(0, 0, 1);
    this.head = new THREE.DirectionalLight(0xffffff, 1.8);
    this.camera.add(this.head);
    this.head.position.set(0.3, 0.5, 1);
    this.scene.add(this.hemi, this.camera);

    this.helpers = new THREE.Group();
    this.scene.add(this.helpers);
    this.setScale(0.1);

    this.model = null;
    this.modelGroup = new THREE.Group();
    this.scene.add(this.modelGroup);
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
  }

  /** The grid (1 cm cells) and turntable axis for an object about `extent` metres across. */
  setScale(extent) {
    this.helpers.clear();
    const half = Math.max(0.05, Math.ceil(extent * 0.8 / 0.01) * 0.01);
    const grid = new THREE.GridHelper(2 * half, Math.round(2 * half / 0.01), 0x6b7480, 0x3a4049);
    grid.rotation.x = Math.PI / 2; // GridHelper lies in XZ; the table plane is XY.
    this.helpers.add(grid);
    const table = new THREE.Mesh(
      new THREE.RingGeometry(half * 0.98, half, 96),
      new THREE.MeshBasicMaterial({ color: 0x8a94a3, side: THREE.DoubleSide }),
    );
    this.helpers.add(table);
    const axis = new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(0, 0, -0.01), new THREE.Vector3(0, 0, Math.max(0.1, extent * 1.3))]);
    this.helpers.add(new THREE.Line(axis, new THREE.LineBasicMaterial({ color: 0xffb300 })));
  }

  resize() {
    const w = Math.max(1, this.container.clientWidth), h = Math.max(1, this.container.clientHeight);
    this.renderer.setSize(w, h, true);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render() {
    this.renderer.render(this.scene, this.camera);
  }

  /** Orbit by `az`, `el` radians about the target (z up), zoom by `scale`. */
  orbitBy(az, el, scale = 1) {
    const t = this.controls.target, off = this.camera.position.clone().sub(t);
    off.applyAxisAngle(new THREE.Vector3(0, 0, 1), az);
    const side = new THREE.Vector3().crossVectors(off, new THREE.Vector3(0, 0, 1)).normalize();
    const tilted = off.clone().applyAxisAngle(side, el);
    if (Math.abs(tilted.clone().normalize().z) < 0.98) off.copy(tilted);
    off.multiplyScalar(scale);
    this.camera.position.copy(t).add(off);
    this.controls.update();
    this.render();
  }

  onKey(e) {
    const step = Math.PI / 24;
    const moves = { ArrowLeft: [-step, 0, 1], ArrowRight: [step, 0, 1], ArrowUp: [0, -step, 1], ArrowDown: [0, step, 1], "+": [0, 0, 0.85], "=": [0, 0, 0.85], "-": [0, 0, 1 / 0.85] };
    const m = moves[e.key];
    if (!m) return;
    e.preventDefault();
    this.orbitBy(...m);
  }

  /** Frame the current model: target its centre, distance to fit. */
  frame() {
    if (!this.model) return;
    // The model's own box (setFromObject would also take in the box helper's unit cube).
    const box = this.modelBox, c = box.getCenter(new THREE.Vector3());
    const size = box.getSize(new THREE.Vector3()).length() || 0.1;
    this.controls.target.copy(c);
    const dir = new THREE.Vector3(0.45, -0.8, 0.45).normalize();
    this.camera.position.copy(c).addScaledVector(dir, size * 1.7);
    this.controls.update();
    this.render();
  }

  /** Parse a PLY (ArrayBuffer) into a geometry; null when it holds no vertex. */
  static parse(buffer) {
    const g = new PLYLoader().parse(buffer);
    return g.getAttribute("position") && g.getAttribute("position").count ? g : null;
  }

  /**
   * Show `geometry` as `kind` ("mesh", "points", "voxels"); `info`: what it is (title, voxel
   * size in metres for voxels, live: true for the running estimate). Replaces the model shown.
   */
  show(geometry, kind, info = {}) {
    const keepView = info.live && this.info && this.info.live && this.info.scanId === info.scanId;
    this.clearModel();
    geometry.computeBoundingBox();
    const box = geometry.boundingBox, size = box.getSize(new THREE.Vector3());
    const colours = !!geometry.getAttribute("color");
    let object;
    if (kind === "mesh" && geometry.index) {
      if (!geometry.getAttribute("normal")) geometry.computeVertexNormals();
      object = new THREE.Mesh(geometry, this.meshMaterial(colours));
    } else if (kind === "voxels") {
      object = this.voxels(geometry, info.voxelSize || 0.002, colours);
    } else {
      // About the spacing of n points spread over the surface of a box this size.
      const n = geometry.getAttribute("position").count, extent = Math.max(size.x, size.y, size.z, 0.01);
      const pointSize = info.pointSize || Math.min(extent / 20, Math.max(0.0006, 0.8 * extent * Math.sqrt(6 / Math.max(n, 1))));
      object = new THREE.Points(geometry, new THREE.PointsMaterial({
        size: pointSize, vertexColors: colours, color: colours ? 0xffffff : (info.live ? LIVE_COLOUR : MODEL_GREY),
      }));
      kind = "points";
    }
    this.model = object;
    this.modelGroup.add(object);
    this.modelBox = box.clone();
    this.box = new THREE.Box3Helper(box, 0x5c6bc0);
    this.modelGroup.add(this.box);
    this.setScale(Math.max(size.x, size.y, size.z));
    this.info = { ...info, kind, colours, count: geometry.getAttribute("position").count, size_m: [size.x, size.y, size.z] };
    if (!keepView) this.frame();
    this.render();
    this.onChange(this.info);
  }

  meshMaterial(colours) {
    const opts = { vertexColors: colours, color: colours ? 0xffffff : MODEL_GREY, wireframe: this.wireframe, side: THREE.DoubleSide };
    return this.lighting ? new THREE.MeshStandardMaterial({ ...opts, roughness: 0.8, metalness: 0 }) : new THREE.MeshBasicMaterial(opts);
  }

  /** One box per voxel centre (instanced), `size` metres on a side. */
  voxels(geometry, size, colours) {
    const pos = geometry.getAttribute("position"), col = geometry.getAttribute("color");
    const box = new THREE.BoxGeometry(size * 0.92, size * 0.92, size * 0.92);
    const mesh = new THREE.InstancedMesh(box, this.voxelMaterial(colours), pos.count);
    const m = new THREE.Matrix4(), c = new THREE.Color();
    for (let i = 0; i < pos.count; i++) {
      m.makeTranslation(pos.getX(i), pos.getY(i), pos.getZ(i));
      mesh.setMatrixAt(i, m);
      if (colours) mesh.setColorAt(i, c.setRGB(col.getX(i), col.getY(i), col.getZ(i)));
    }
    mesh.userData.points = geometry;
    return mesh;
  }

  voxelMaterial(colours) {
    const mat = this.meshMaterial(false);
    if (colours) mat.color.set(0xffffff); // the instance colours carry the colour
    return mat;
  }

  setWireframe(on) {
    this.wireframe = on;
    this.restyle();
  }

  setLighting(on) {
    this.lighting = on;
    this.restyle();
  }

  restyle() {
    if (this.model && (this.model.isMesh || this.model.isInstancedMesh)) {
      const old = this.model.material;
      this.model.material = this.model.isInstancedMesh ? this.voxelMaterial(this.info.colours) : this.meshMaterial(this.info.colours);
      old.dispose();
    }
    this.render();
  }

  clearModel() {
    for (const o of [...this.modelGroup.children]) {
      this.modelGroup.remove(o);
      if (o.geometry) o.geometry.dispose();
      if (o.material) o.material.dispose();
    }
    this.model = null;
  }

  clear() {
    this.clearModel();
    this.info = null;
    this.render();
    this.onChange(null);
  }
}
