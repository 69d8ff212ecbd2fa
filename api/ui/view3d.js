// The 3D view of a job: the combined model's points (combined/gis/points.las) and cameras
// (combined/gis/cameras_opk.txt), both in the job's output CRS, drawn with three.js (installed from the
// npm registry by scripts/setup.sh). draw() returns a stop function with a report of what it drew.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

/** {xyz: Float32Array(3n), rgb: Float32Array(3n), count} of a LAS 1.4 file (point formats 6-8: RGB at 30). */
export function parseLas(buf) {
  const v = new DataView(buf);
  const magic = String.fromCharCode(v.getUint8(0), v.getUint8(1), v.getUint8(2), v.getUint8(3));
  if (magic !== "LASF") throw new Error("not a LAS file");
  const offset = v.getUint32(96, true), format = v.getUint8(104) & 0x3f, length = v.getUint16(105, true);
  const count = Number(v.getBigUint64(247, true));
  const scale = [0, 1, 2].map((i) => v.getFloat64(131 + 8 * i, true));
  const origin = [0, 1, 2].map((i) => v.getFloat64(155 + 8 * i, true));
  const xyz = new Float64Array(3 * count), rgb = new Float32Array(3 * count);
  const colour = format >= 7 ? 30 : -1;
  for (let i = 0; i < count; i++) {
    const o = offset + i * length;
    for (let k = 0; k < 3; k++) xyz[3 * i + k] = v.getInt32(o + 4 * k, true) * scale[k] + origin[k];
    for (let k = 0; k < 3; k++) rgb[3 * i + k] = colour >= 0 ? v.getUint16(o + colour + 2 * k, true) / 65535 : 0.7;
  }
  return { xyz, rgb, count };
}

/** The Gaussians of a 3DGS PLY (binary little endian, as gsplat and midview write it) as points:
 * {xyz, rgb, count, total}: centres of those with opacity over minOpacity, coloured by their SH DC term. */
export function parsePly(buf, minOpacity = 0.2) {
  const head = new TextDecoder().decode(new Uint8Array(buf, 0, Math.min(buf.byteLength, 65536)));
  const end = head.indexOf("end_header\n");
  if (!head.startsWith("ply") || end < 0) throw new Error("not a PLY file");
  if (!head.includes("format binary_little_endian")) throw new Error("only binary little-endian PLY files");
  const sizes = { float: 4, float32: 4, double: 8, uchar: 1, uint8: 1, char: 1, short: 2, ushort: 2, int: 4, uint: 4 };
  let total = 0, stride = 0;
  const at = {}, types = {};
  for (const line of head.slice(0, end).split("\n")) {
    const w = line.trim().split(/\s+/);
    if (w[0] === "element") { if (w[1] !== "vertex") break; total = Number(w[2]); }
    if (w[0] === "property") { at[w[2]] = stride; types[w[2]] = w[1]; stride += sizes[w[1]] || 4; }
  }
  for (const k of ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]) {
    if (!(k in at) || !["float", "float32"].includes(types[k])) throw new Error(`PLY without a float ${k}`);
  }
  const v = new DataView(buf, end + "end_header\n".length);
  const C0 = 0.28209479177387814, xyz = [], rgb = [];
  for (let i = 0; i < total; i++) {
    const o = i * stride;
    const opacity = 1 / (1 + Math.exp(-v.getFloat32(o + at.opacity, true)));
    if (opacity < minOpacity) continue;
    xyz.push(v.getFloat32(o + at.x, true), v.getFloat32(o + at.y, true), v.getFloat32(o + at.z, true));
    for (const k of ["f_dc_0", "f_dc_1", "f_dc_2"]) rgb.push(Math.min(1, Math.max(0, 0.5 + C0 * v.getFloat32(o + at[k], true))));
  }
  return { xyz: Float64Array.from(xyz), rgb: Float32Array.from(rgb), count: xyz.length / 3, total };
}

/** [{name, set, c: [x, y, z], view: [dx, dy, dz]}] of an omega/phi/kappa file (degrees; camera looks along -z). */
export function parseOpk(text) {
  const rad = Math.PI / 180;
  return text.split("\n").filter((l) => l.trim() && !l.startsWith("#")).map((l) => {
    const [name, x, y, z, o, p, k] = l.trim().split(/\s+/);
    const [w, f, q] = [o, p, k].map((a) => Number(a) * rad);
    // the third column of Rx(w) Ry(f) Rz(q), negated
    const r02 = Math.sin(f), r12 = -Math.sin(w) * Math.cos(f), r22 = Math.cos(w) * Math.cos(f);
    void q;
    return { name, set: name.split("/")[0], c: [Number(x), Number(y), Number(z)], view: [-r02, -r12, -r22] };
  });
}

export function webglAvailable() {
  try { const c = document.createElement("canvas"); return !!(c.getContext("webgl2") || c.getContext("webgl")); }
  catch { return false; }
}

/** The bulk of n points xyz (3n): {centre: per-axis medians, extent: the 95th percentile of the points'
 * largest offset from it}, so that a few outliers (floaters, far tie points) do not shrink the model to a
 * speck; read on at most 20000 points spread over the set. */
export function bulk(xyz, n) {
  if (!n) return { centre: [0, 0, 0], extent: 1 };
  const step = Math.max(1, Math.floor(n / 20000)), idx = [];
  for (let i = 0; i < n; i += step) idx.push(i);
  const quantile = (values, q) => { values.sort((a, b) => a - b); return values[Math.min(values.length - 1, Math.floor(q * values.length))]; };
  const centre = [0, 1, 2].map((k) => quantile(idx.map((i) => xyz[3 * i + k]), 0.5));
  const offsets = idx.map((i) => Math.max(...[0, 1, 2].map((k) => Math.abs(xyz[3 * i + k] - centre[k]))));
  return { centre, extent: Math.max(1e-3, quantile(offsets, 0.95)) };
}

/** Draw points and cameras into `container`; returns a function that stops the rendering. A click (not a
 * drag) on a camera calls onPick(its name); stop.screenOf(name) is where a camera is drawn (canvas px). */
export function draw(container, las, cams, onPick = null) {
  const n = las.count;
  const { centre, extent } = bulk(las.xyz, n);
  const pos = new Float32Array(3 * n);
  for (let i = 0; i < 3 * n; i++) pos[i] = las.xyz[i] - centre[i % 3];
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xf3f4f6);
  const geom = new THREE.BufferGeometry();
  geom.setAttribute("position", new THREE.BufferAttribute(pos, 3));
  geom.setAttribute("color", new THREE.BufferAttribute(las.rgb, 3));
  scene.add(new THREE.Points(geom, new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, vertexColors: true })));
  const lines = [], colours = [];
  for (const cam of cams) {
    const c = cam.c.map((x, k) => x - centre[k]);
    const len = extent * 0.05;
    lines.push(...c, ...c.map((x, k) => x + cam.view[k] * len));
    const col = cam.set === "aerial" ? [0.14, 0.34, 0.77] : [0.1, 0.5, 0.22];
    colours.push(...col, ...col);
  }
  const lg = new THREE.BufferGeometry();
  lg.setAttribute("position", new THREE.BufferAttribute(new Float32Array(lines), 3));
  lg.setAttribute("color", new THREE.BufferAttribute(new Float32Array(colours), 3));
  scene.add(new THREE.LineSegments(lg, new THREE.LineBasicMaterial({ vertexColors: true })));
  const camMarkers = new THREE.BufferGeometry();
  camMarkers.setAttribute("position", new THREE.BufferAttribute(new Float32Array(cams.flatMap((c) => c.c.map((x, k) => x - centre[k]))), 3));
  camMarkers.setAttribute("color", new THREE.BufferAttribute(new Float32Array(cams.flatMap((c) => c.set === "aerial" ? [0.14, 0.34, 0.77] : [0.1, 0.5, 0.22])), 3));
  const markers = new THREE.Points(camMarkers, new THREE.PointsMaterial({ size: 7, sizeAttenuation: false, vertexColors: true }));
  scene.add(markers);

  const width = container.clientWidth || 800, height = Math.max(320, Math.min(640, width * 0.6));
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  renderer.setSize(width, height);
  container.append(renderer.domElement);
  const camera = new THREE.PerspectiveCamera(50, width / height, extent / 1000, extent * 20);
  camera.up.set(0, 0, 1);  // the output CRS: z up
  camera.position.set(extent * 1.2, -extent * 1.6, extent * 1.4);
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.target.set(0, 0, 0);
  let running = true;
  const loop = () => { if (!running) return; controls.update(); renderer.render(scene, camera); requestAnimationFrame(loop); };
  loop();
  // a click on a camera: the nearest marker within 8 px of the pointer (a drag turns the view instead)
  const screenOf = (i) => {
    const p = new THREE.Vector3(...cams[i].c.map((x, k) => x - centre[k])).project(camera);
    return [(p.x + 1) / 2 * width, (1 - p.y) / 2 * height];
  };
  let down = null;
  renderer.domElement.addEventListener("pointerdown", (e) => { down = [e.offsetX, e.offsetY]; });
  renderer.domElement.addEventListener("pointerup", (e) => {
    if (!onPick || !down || Math.hypot(e.offsetX - down[0], e.offsetY - down[1]) > 4) return;
    let best = null;
    cams.forEach((c, i) => {
      const [x, y] = screenOf(i), d = Math.hypot(x - e.offsetX, y - e.offsetY);
      if (d <= 8 && (!best || d < best.d)) best = { d, name: c.name };
    });
    if (best) onPick(best.name);
  });
  void markers;
  const report = { points: n, extent, cameras: cams.length, aerial: cams.filter((c) => c.set === "aerial").length,
    ground: cams.filter((c) => c.set === "ground").length, names: cams.map((c) => c.name), canvas: renderer.domElement };
  const stop = () => { running = false; renderer.dispose(); };
  stop.report = report;
  stop.screenOf = (name) => { const i = cams.findIndex((c) => c.name === name); return i < 0 ? null : screenOf(i); };
  return stop;
}
