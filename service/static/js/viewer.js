// The 3D view of a result (three.js): the mesh shaded, edge points and edge curves over it, input
// points and normals on a bounded sample; orbit and zoom (OrbitControls), reset. It draws only
// when something changes, so an idle page costs nothing.

import * as THREE from 'three';
import {OrbitControls} from 'three/addons/controls/OrbitControls.js';

export const MAX_DRAWN_POINTS = 200000; // edge points drawn at most
export const MAX_NORMALS = 10000; // normals drawn at most

const COLOURS = {
  background: 0xf1f3f6, mesh: 0xa9bccf, edges: 0xff3d00, points: 0x38434f, normals: 0x12a150,
  convex: 0xffb300, concave: 0xd500f9,
};

export class Viewer {
  constructor(canvas) {
    this.canvas = canvas;
    // preserveDrawingBuffer: the picture stays readable (screenshots, toDataURL) after it is drawn.
    this.renderer = new THREE.WebGLRenderer({canvas, antialias: true, preserveDrawingBuffer: true});
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.setClearColor(COLOURS.background);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 100);
    this.scene.add(this.camera);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x6b7785, 1.6));
    const headlight = new THREE.DirectionalLight(0xffffff, 1.8);
    headlight.position.set(0.5, 1, 1.5); // follows the camera
    this.camera.add(headlight);
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.addEventListener('change', () => this.render());
    this.layers = {}; // name -> Object3D
    this.visible = {mesh: true, edges: true, curves: true, points: false, normals: false};
    this.scale = 1;
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.resize();
  }

  resize() {
    const width = this.canvas.clientWidth || 640;
    const height = this.canvas.clientHeight || 480;
    this.renderer.setSize(width, height, false);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  /** Draw at the next frame (several changes in one frame draw once). */
  render() {
    if (this.pending) return;
    this.pending = requestAnimationFrame(() => {
      this.pending = null;
      this.renderer.render(this.scene, this.camera);
      this.canvas.dataset.frames = String(Number(this.canvas.dataset.frames || 0) + 1);
    });
  }

  clear() {
    for (const name of Object.keys(this.layers)) this.remove(name);
    this.render();
  }

  remove(name) {
    const object = this.layers[name];
    if (!object) return;
    this.scene.remove(object);
    object.geometry?.dispose();
    object.material?.dispose();
    delete this.layers[name];
  }

  put(name, object) {
    this.remove(name);
    object.visible = this.visible[name] !== false;
    this.layers[name] = object;
    this.scene.add(object);
    this.render();
  }

  has(name) { return name in this.layers; }

  setVisible(name, visible) {
    this.visible[name] = visible;
    if (this.layers[name]) this.layers[name].visible = visible;
    this.render();
  }

  /** The mesh: {positions, index} (formats.parseObj) in one indexed BufferGeometry. */
  setMesh({positions, index}) {
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
    geometry.setIndex(new THREE.BufferAttribute(index, 1));
    geometry.computeVertexNormals();
    geometry.computeBoundingSphere();
    const material = new THREE.MeshStandardMaterial({
      color: COLOURS.mesh, roughness: 0.75, metalness: 0.0, side: THREE.DoubleSide,
      // Pushed back a little in depth, so points lying on the surface are drawn over it.
      polygonOffset: true, polygonOffsetFactor: 1.5, polygonOffsetUnits: 2,
    });
    this.put('mesh', new THREE.Mesh(geometry, material));
    this.frame();
  }

  /** Edge points: [[x, y, z], ...], at most MAX_DRAWN_POINTS of them drawn. */
  setEdgePoints(points) {
    const step = Math.max(1, Math.ceil(points.length / MAX_DRAWN_POINTS));
    const kept = Math.ceil(points.length / step);
    const positions = new Float32Array(kept * 3);
    for (let i = 0, j = 0; i < points.length; i += step, j += 1) positions.set(points[i], j * 3);
    this.put('edges', pointCloud(positions, COLOURS.edges, 4.5));
    return kept;
  }

  /** Edge curves: [{points: [[x, y, z], ...], angle, convex}, ...] as line segments. */
  setCurves(curves) {
    const convex = [];
    const concave = [];
    for (const curve of curves) {
      const target = curve.convex === false ? concave : convex;
      const points = curve.points || [];
      for (let i = 0; i + 1 < points.length; i += 1) target.push(...points[i], ...points[i + 1]);
    }
    const group = new THREE.Group();
    for (const [segments, colour] of [[convex, COLOURS.convex], [concave, COLOURS.concave]]) {
      if (!segments.length) continue;
      const geometry = new THREE.BufferGeometry();
      geometry.setAttribute('position', new THREE.Float32BufferAttribute(segments, 3));
      group.add(new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({color: colour, depthTest: false})));
    }
    group.renderOrder = 2;
    this.put('curves', group);
  }

  /** Input points (a sample): Float32Array of x y z. */
  setInputPoints(positions) {
    this.put('points', pointCloud(positions, COLOURS.points, 2));
    if (!this.has('mesh')) this.frame();
  }

  /** Normals as short segments at (a sample of) ``positions``, of a length that suits the shape. */
  setNormals(positions, normals) {
    const count = Math.min(positions.length / 3, normals.length / 3);
    const step = Math.max(1, Math.ceil(count / MAX_NORMALS));
    const length = this.scale * 0.04;
    const segments = [];
    for (let i = 0; i < count; i += step) {
      const [x, y, z] = [positions[i * 3], positions[i * 3 + 1], positions[i * 3 + 2]];
      const [nx, ny, nz] = [normals[i * 3], normals[i * 3 + 1], normals[i * 3 + 2]];
      if (!Number.isFinite(nx + ny + nz)) continue;
      segments.push(x, y, z, x + nx * length, y + ny * length, z + nz * length);
    }
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute('position', new THREE.Float32BufferAttribute(segments, 3));
    this.put('normals', new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({color: COLOURS.normals})));
    return segments.length / 6;
  }

  /** Put the camera back to a three-quarter view of everything drawn. */
  frame() {
    const box = new THREE.Box3();
    for (const object of Object.values(this.layers)) box.expandByObject(object);
    if (box.isEmpty()) return;
    const sphere = box.getBoundingSphere(new THREE.Sphere());
    const radius = Math.max(sphere.radius, 1e-6);
    this.scale = radius * 2;
    const distance = radius / Math.sin(THREE.MathUtils.degToRad(this.camera.fov / 2)) * 1.05;
    this.camera.near = distance / 100;
    this.camera.far = distance * 100;
    this.camera.position.copy(sphere.center).add(new THREE.Vector3(1, 0.8, 1.3).normalize().multiplyScalar(distance));
    this.camera.up.set(0, 1, 0);
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(sphere.center);
    this.controls.minDistance = radius * 0.05;
    this.controls.maxDistance = distance * 20;
    this.controls.update();
    this.render();
  }
}

function pointCloud(positions, colour, size) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
  geometry.computeBoundingSphere();
  const material = new THREE.PointsMaterial({color: colour, size, sizeAttenuation: false});
  return new THREE.Points(geometry, material);
}
