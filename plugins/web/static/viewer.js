// btforge view: relight a model in relight's web layout (info.json + coefficient planes) with WebGL.
// The decoding follows the layout: coefficient = (byte / 255 - bias) * scale, planes packed three per image,
// relit value = sum of coefficient x basis(light); models marked "transfer": "linear" are sRGB-encoded for display.
// Neural layouts (latent codes and a decoder network) are evaluated per pixel by neural.js.
"use strict";

const params = new URLSearchParams(location.search);
const state = { models: [], current: -1, light: [0, 0, 1], zoom: 1, pan: [0, 0], info: null, gl: null,
                program: null, textures: [], fitted: false };
window.btforgeViewer = state;

function showMessage(text) {
  const box = document.getElementById("message");
  box.textContent = text;
  box.style.display = text ? "block" : "none";
}

function fail(text) {
  showMessage(text);
  document.body.dataset.state = "error";
}

// ---------------------------------------------------------------------------------------------- bases

function ptmWeights(l) {
  const [x, y] = l;
  return [1, x, y, x * x, x * y, y * y];
}

function shWeights(l) {
  const [x, y, z] = l;
  const a = 0.5 * Math.sqrt(3 / Math.PI), b = 0.5 * Math.sqrt(15 / Math.PI);
  return [0.5 / Math.sqrt(Math.PI), a * x, a * z, a * y, b * x * y, b * x * z,
          0.5 * Math.sqrt(5 / Math.PI) * (3 * z * z - 1), b * y * z, 0.5 * b * (y * y - x * x)];
}

function hshWeights(l, terms) {
  const PI = Math.PI;
  let phi = Math.atan2(l[1], l[0]);
  if (phi < 0) phi += 2 * PI;
  const theta = Math.min(Math.acos(Math.max(-1, Math.min(1, l[2]))), PI / 2 - 0.15);
  const ct = Math.cos(theta), root = Math.sqrt(Math.max(ct - ct * ct, 0));
  const w = [1 / Math.sqrt(2 * PI), Math.sqrt(6 / PI) * Math.cos(phi) * root, Math.sqrt(3 / (2 * PI)) * (2 * ct - 1),
             Math.sqrt(6 / PI) * Math.sin(phi) * root, Math.sqrt(30 / PI) * Math.cos(2 * phi) * (ct * ct - ct),
             Math.sqrt(30 / PI) * Math.cos(phi) * (2 * ct - 1) * root,
             Math.sqrt(5 / (2 * PI)) * (6 * ct * ct - 6 * ct + 1),
             Math.sqrt(30 / PI) * Math.sin(phi) * (2 * ct - 1) * root,
             Math.sqrt(30 / PI) * Math.sin(2 * phi) * (ct * ct - ct)];
  return w.slice(0, terms);
}

// Weight of every plane (nplanes of them) for a light: what multiplies each decoded coefficient.
function planeWeights(info, l) {
  const n = info.nplanes, out = new Float32Array(n);
  if (info.type === "ptm" && info.colorspace === "lrgb") {
    const b = ptmWeights(l);
    for (let k = 0; k < 6; k++) out[3 + k] = b[k];
    return out;
  }
  const b = info.type === "ptm" ? ptmWeights(l) : info.type === "sh" ? shWeights(l) : hshWeights(l, n / 3);
  for (let p = 0; p < n; p++) out[p] = b[Math.floor(p / 3)] || 0;
  return out;
}

// rbf and bilinear (relight's mrgb / mycc): per-plane colour weights read from a light table in info.json.
// basis: (nplanes + 1) x D x 3 bytes, row 0 the mean (byte / 255), row p + 1 component p ((byte - 127) / range[p]).
function lightTable(info) {
  if (info._table) return info._table;
  const n = info.nplanes, d = info.type === "rbf" ? info.lights.length / 3 : info.resolution * info.resolution;
  const range = info.materials[0].range, table = new Float32Array((n + 1) * d * 3);
  for (let i = 0; i < table.length; i++) {
    const p = Math.floor(i / (d * 3));
    table[i] = p === 0 ? info.basis[i] / 255 : (info.basis[i] - 127) / range[p - 1];
  }
  info._table = { table, d };
  return info._table;
}

// Normalised Gaussian weights exp(-|l - l_i|^2 / sigma^2) over the lights; shares below 0.001 are dropped.
function rbfWeights(info, l) {
  const n = info.lights.length / 3, d2 = new Float64Array(n);
  let least = Infinity;
  for (let i = 0; i < n; i++) {
    const dx = l[0] - info.lights[3 * i], dy = l[1] - info.lights[3 * i + 1], dz = l[2] - info.lights[3 * i + 2];
    d2[i] = dx * dx + dy * dy + dz * dz;
    least = Math.min(least, d2[i]);
  }
  const w = d2.map((v) => Math.exp(-(v - least) / (info.sigma * info.sigma)));
  const total = w.reduce((a, b) => a + b, 0);
  const kept = w.map((v) => (v / total > 0.001 ? v : 0));
  const sum = kept.reduce((a, b) => a + b, 0);
  return kept.map((v) => v / sum);
}

// Bilinear weights over the resolution^2 grid of the octahedral map (rotated 45 degrees), node x + y * res.
function bilinearWeights(info, l) {
  const res = info.resolution, w = new Float64Array(res * res);
  const z = Math.max(l[2], 0), s = Math.abs(l[0]) + Math.abs(l[1]) + z || 1;
  const clampTo = (v, hi) => Math.min(hi, Math.max(0, v));
  const x = clampTo(((l[0] + l[1]) / s + 1) * 0.5 * (res - 1), res - 1);
  const y = clampTo(((l[1] - l[0]) / s + 1) * 0.5 * (res - 1), res - 1);
  const sx = clampTo(Math.floor(x), res - 2), sy = clampTo(Math.floor(y), res - 2), dx = x - sx, dy = y - sy;
  w[sx + sy * res] += (1 - dx) * (1 - dy);
  w[sx + 1 + sy * res] += dx * (1 - dy);
  w[sx + (sy + 1) * res] += (1 - dx) * dy;
  w[sx + 1 + (sy + 1) * res] += dx * dy;
  return w;
}

// The basis at the light in RGB: (nplanes + 1) triples, the mean first (YCoCg converted for mycc).
function tableWeights(info, l) {
  const { table, d } = lightTable(info), n = info.nplanes, out = new Float32Array((n + 1) * 3);
  const w = info.type === "rbf" ? rbfWeights(info, l) : bilinearWeights(info, l);
  for (let p = 0; p <= n; p++) {
    const acc = [0, 0, 0];
    for (let i = 0; i < d; i++) {
      if (!w[i]) continue;
      for (let k = 0; k < 3; k++) acc[k] += w[i] * table[(p * d + i) * 3 + k];
    }
    if (info.colorspace === "mycc") {
      const [y, co, cg] = acc, g = y + cg / 2, b = y - cg / 2 - co / 2;
      acc[0] = b + co; acc[1] = g; acc[2] = b;
    }
    out.set(acc, 3 * p);
  }
  return out;
}

function usesTable(info) {
  return info.type === "rbf" || info.type === "bilinear" || info.type === "bln";
}

// ---------------------------------------------------------------------------------------------- WebGL

const VERTEX = `
attribute vec2 a_uv;
uniform vec2 u_offset, u_size, u_canvas;
uniform float u_zoom;
varying vec2 v_uv;
void main() {
  vec2 px = u_offset + u_zoom * a_uv * u_size;
  gl_Position = vec4(px.x / u_canvas.x * 2.0 - 1.0, 1.0 - px.y / u_canvas.y * 2.0, 0.0, 1.0);
  v_uv = a_uv;
}`;

function fragmentSource(info) {
  const n = info.nplanes, images = Math.ceil(n / 3);
  let src = "precision highp float;\nvarying vec2 v_uv;\n";
  src += `uniform float u_w[${n}], u_scale[${n}], u_bias[${n}];\nuniform vec3 u_w3[${n + 1}];\n`;
  for (let j = 0; j < images; j++) src += `uniform sampler2D u_plane${j};\n`;
  src += "vec3 toSrgb(vec3 c) { c = clamp(c, 0.0, 1.0);\n" +
         "  return mix(c * 12.92, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), c)); }\n";
  src += "void main() {\n  vec3 rgb = vec3(0.0); float lum = 0.0; vec3 t; vec3 albedo = vec3(1.0);\n";
  if (usesTable(info)) src += "  rgb = u_w3[0];\n";
  const lrgb = info.type === "ptm" && info.colorspace === "lrgb";
  for (let j = 0; j < images; j++) {
    src += `  t = texture2D(u_plane${j}, v_uv).rgb;\n`;
    for (let c = 0; c < 3; c++) {
      const p = 3 * j + c;
      if (p >= n) break;
      const coeff = `(t[${c}] - u_bias[${p}]) * u_scale[${p}]`;
      if (usesTable(info)) src += `  rgb += u_w3[${p + 1}] * ${coeff};\n`;
      else if (lrgb && p < 3) src += `  albedo[${c}] = ${coeff};\n`;
      else if (lrgb) src += `  lum += u_w[${p}] * ${coeff};\n`;
      else src += `  rgb[${c}] += u_w[${p}] * ${coeff};\n`;
    }
  }
  if (lrgb) src += "  rgb = lum * albedo;\n";
  const linear = info.btforge && info.btforge.transfer === "linear";
  src += linear ? "  gl_FragColor = vec4(toSrgb(max(rgb, 0.0)), 1.0);\n}\n"
                : "  gl_FragColor = vec4(clamp(rgb, 0.0, 1.0), 1.0);\n}\n";
  return src;
}

function compile(gl, type, source) {
  const shader = gl.createShader(type);
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error("shader: " + gl.getShaderInfoLog(shader));
  return shader;
}

function setupGl() {
  const canvas = document.getElementById("view");
  const gl = canvas.getContext("webgl", { preserveDrawingBuffer: true, antialias: false, premultipliedAlpha: false });
  if (!gl) throw new Error("WebGL is not available in this browser");
  const ext = gl.getExtension("WEBGL_debug_renderer_info");
  document.body.dataset.renderer = ext ? gl.getParameter(ext.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
  const buffer = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([0, 0, 1, 0, 0, 1, 1, 1]), gl.STATIC_DRAW);
  state.gl = gl;
}

function loadImage(url) {
  return new Promise((resolve, reject) => {
    const img = new Image();
    img.onload = () => resolve(img);
    img.onerror = () => reject(new Error("cannot load " + url));
    img.src = url;
  });
}

async function loadModel(index) {
  const gl = state.gl, model = state.models[index];
  document.body.dataset.state = "loading";
  showMessage("");
  let info;
  try {
    const response = await fetch(model.url + "info.json");
    if (!response.ok) throw new Error(`info.json: HTTP ${response.status}`);
    info = await response.json();
    const neural = info.type === "neural";
    for (const key of ["width", "height", "type"].concat(neural ? [] : ["nplanes", "colorspace"]))
      if (info[key] === undefined) throw new Error(`info.json has no '${key}'`);
    if (!["ptm", "sh", "hsh", "rbf", "bilinear", "bln", "neural"].includes(info.type))
      throw new Error(`type '${info.type}' is not supported`);
    if (usesTable(info) && !(info.basis && info.materials && info.materials[0].range))
      throw new Error(`a ${info.type} layout needs 'basis' and materials[0].range`);
    const material = (info.materials || [])[0] || {};
    if (!neural && (!material.scale || material.scale.length < info.nplanes || !material.bias ||
                    material.bias.length < info.nplanes))
      throw new Error("materials[0] must give a scale and a bias per plane");
    // a neural layout's code images are plane_1 .. (OpenLIME's neural layer names its output plane_0)
    const first = neural ? 1 : 0, count = Math.ceil((neural ? info.planes : info.nplanes) / 3);
    const images = await Promise.all(Array.from({ length: count },
      (_, j) => loadImage(`${model.url}plane_${first + j}.${info.format || "jpg"}`)));
    for (const t of state.textures) gl.deleteTexture(t);
    if (state.info && state.info._neural) gl.deleteTexture(state.info._neural.tex);
    state.textures = images.map((img) => {
      const tex = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.pixelStorei(gl.UNPACK_COLORSPACE_CONVERSION_WEBGL, gl.NONE);
      gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, img);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
      return tex;
    });
    const program = gl.createProgram();
    gl.attachShader(program, compile(gl, gl.VERTEX_SHADER, VERTEX));
    const source = neural ? neuralPrepare(gl, info) : fragmentSource(info);
    gl.attachShader(program, compile(gl, gl.FRAGMENT_SHADER, source));
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error("program: " + gl.getProgramInfoLog(program));
    state.program = program;
    state.info = info;
    state.current = index;
  } catch (error) {
    state.info = null;
    fail(`Could not load model '${model.name}': ${error.message}`);
    draw();
    return;
  }
  if (!state.fitted) fitView();
  draw();
  document.body.dataset.state = "ready";
}

function fitView() {
  const canvas = document.getElementById("view"), info = state.info;
  if (!info) return;
  const top = params.get("bar") === "0" ? 0 : 30;
  state.zoom = params.has("zoom") ? Number(params.get("zoom"))
                                  : Math.min(canvas.width / info.width, (canvas.height - top) / info.height);
  state.pan = [params.has("zoom") ? 0 : (canvas.width - state.zoom * info.width) / 2,
               params.has("zoom") ? top : top + (canvas.height - top - state.zoom * info.height) / 2];
  state.fitted = true;
}

function draw() {
  const gl = state.gl, canvas = gl.canvas;
  gl.viewport(0, 0, canvas.width, canvas.height);
  gl.clearColor(0.125, 0.125, 0.125, 1);
  gl.clear(gl.COLOR_BUFFER_BIT);
  const info = state.info;
  document.getElementById("light").textContent = "light " + state.light.map((v) => v.toFixed(3)).join(", ");
  if (!info) return;
  const prog = state.program;
  gl.useProgram(prog);
  const loc = gl.getAttribLocation(prog, "a_uv");
  gl.enableVertexAttribArray(loc);
  gl.vertexAttribPointer(loc, 2, gl.FLOAT, false, 0, 0);
  gl.uniform2f(gl.getUniformLocation(prog, "u_offset"), state.pan[0], state.pan[1]);
  gl.uniform2f(gl.getUniformLocation(prog, "u_size"), info.width, info.height);
  gl.uniform2f(gl.getUniformLocation(prog, "u_canvas"), canvas.width, canvas.height);
  gl.uniform1f(gl.getUniformLocation(prog, "u_zoom"), state.zoom);
  if (info.type === "neural") neuralUniforms(gl, prog, info, state.light, state.textures.length);
  else planeUniforms(gl, prog, info);
  state.textures.forEach((tex, j) => {
    gl.activeTexture(gl.TEXTURE0 + j);
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.uniform1i(gl.getUniformLocation(prog, `u_plane${j}`), j);
  });
  gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
}

// The basis weights at the light and every plane's scale and bias (the layouts of coefficient planes).
function planeUniforms(gl, prog, info) {
  const m = info.materials[0];
  if (usesTable(info)) gl.uniform3fv(gl.getUniformLocation(prog, "u_w3[0]"), tableWeights(info, state.light));
  else gl.uniform1fv(gl.getUniformLocation(prog, "u_w[0]"), planeWeights(info, state.light));
  gl.uniform1fv(gl.getUniformLocation(prog, "u_scale[0]"), new Float32Array(m.scale.slice(0, info.nplanes)));
  gl.uniform1fv(gl.getUniformLocation(prog, "u_bias[0]"), new Float32Array(m.bias.slice(0, info.nplanes)));
}

// The light follows the pointer over the canvas: x right, y up, on the unit disc (outside it: the horizon).
function setLight(x, y) {
  const r = Math.hypot(x, y);
  if (r > 1) { x /= r; y /= r; }
  state.light = [x, y, Math.sqrt(Math.max(0, 1 - x * x - y * y))];
  draw();
}
state.setLight = setLight;

function resize() {
  const canvas = document.getElementById("view");
  canvas.width = window.innerWidth;
  canvas.height = window.innerHeight;
  canvas.style.width = canvas.width + "px";
  canvas.style.height = canvas.height + "px";
  if (state.gl) draw();
}

function installControls() {
  const canvas = document.getElementById("view");
  let drag = null;
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointerdown", (e) => {
    drag = { pan: e.shiftKey || e.button === 2, x: e.clientX, y: e.clientY, start: state.pan.slice() };
    canvas.setPointerCapture(e.pointerId);
    if (!drag.pan) lightAt(e);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    if (drag.pan) {
      state.pan = [drag.start[0] + e.clientX - drag.x, drag.start[1] + e.clientY - drag.y];
      draw();
    } else lightAt(e);
  });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const factor = Math.exp(-e.deltaY * 0.002);
    state.pan = [e.clientX - (e.clientX - state.pan[0]) * factor, e.clientY - (e.clientY - state.pan[1]) * factor];
    state.zoom *= factor;
    draw();
  }, { passive: false });
  function lightAt(e) {
    const rect = canvas.getBoundingClientRect();
    setLight(((e.clientX - rect.left) / rect.width) * 2 - 1, 1 - ((e.clientY - rect.top) / rect.height) * 2);
  }
  document.getElementById("snapshot").addEventListener("click", () => {
    const link = document.createElement("a");
    link.download = `${state.models[state.current] ? state.models[state.current].name : "view"}.png`;
    link.href = canvas.toDataURL("image/png");
    link.click();
  });
  document.getElementById("reset").addEventListener("click", () => {
    state.fitted = false;
    fitView();
    setLight(0, 0);
  });
  document.getElementById("models").addEventListener("change", (e) => loadModel(Number(e.target.value)));
}

async function main() {
  if (params.get("bar") === "0") document.getElementById("bar").classList.add("hidden");
  resize();
  window.addEventListener("resize", resize);
  try {
    setupGl();
  } catch (error) {
    fail(error.message);
    return;
  }
  installControls();
  try {
    const response = await fetch("models.json");
    state.models = await response.json();
  } catch (error) {
    fail("Could not list the models: " + error.message);
    return;
  }
  const select = document.getElementById("models");
  state.models.forEach((m, i) => select.add(new Option(m.name, String(i))));
  if (params.has("light")) {
    const [x, y] = params.get("light").split(",").map(Number);
    state.light = [x, y, Math.sqrt(Math.max(0, 1 - x * x - y * y))];
  }
  const first = Number(params.get("model") || 0);
  select.value = String(first);
  await loadModel(first);
}

main();
