// btforge view: neural layouts ("type": "neural", OpenLIME's neural layer format; see btforge.plugins.neural.weblayout).
// Every pixel runs the decoder on its code: code = byte / 255 * (max - min) + min from the images plane_1 ..;
// the layers' weights (output-major, padded to multiples of 4) live in a float texture, one row per output unit.
// The light enters through uniforms only, computed here per light: a light decoder's light inputs fold into the
// first layer's bias, and a harmonics decoder's output coefficients, weighted by the harmonics at the light,
// fold into a 3-output last layer.
"use strict";

// Real spherical harmonics of bands 0 .. order - 1 at the unit direction l, index l^2 + l + m, no Condon-Shortley
// phase, m > 0: cos(m phi), m < 0: sin(|m| phi) (the convention of btforge.numerics.real_sh).
function realSh(order, l) {
  const [x, y, z] = l, out = new Float64Array(order * order);
  const factorial = (n) => { let f = 1; for (let i = 2; i <= n; i++) f *= i; return f; };
  let cosM = 1, sinM = 0, pmm = 1;
  for (let m = 0; m < order; m++) {
    if (m > 0) {
      [cosM, sinM] = [x * cosM - y * sinM, x * sinM + y * cosM];
      pmm *= 2 * m - 1;
    }
    let prev = 0, cur = pmm;
    for (let band = m; band < order; band++) {
      if (band === m + 1) [prev, cur] = [cur, (2 * m + 1) * z * cur];
      else if (band > m + 1) [prev, cur] = [cur, ((2 * band - 1) * z * cur - (band + m - 1) * prev) / (band - m)];
      const norm = Math.sqrt((2 * band + 1) / (4 * Math.PI) * factorial(band - m) / factorial(band + m));
      if (m === 0) out[band * band + band] = norm * cur;
      else {
        out[band * band + band + m] = Math.SQRT2 * norm * cur * cosM;
        out[band * band + band - m] = Math.SQRT2 * norm * cur * sinM;
      }
    }
  }
  return out;
}

function pad4(n) {
  return Math.ceil(n / 4) * 4;
}

// The decoder a neural info.json holds: its kind, light order and layers {rows, cols, w, b} as stored.
function neuralNetwork(info) {
  const extra = info.btforge || {};
  const decoder = extra.decoder || "light", order = extra.light_order || 0;
  const sizes = extra.layer_sizes || [info.planes + 2, info.samples, info.samples, 3];
  if (!["light", "harmonics"].includes(decoder)) throw new Error(`decoder '${decoder}' is not light or harmonics`);
  if (sizes.length < 3) throw new Error(`the decoder needs a hidden layer, found layer sizes ${sizes}`);
  if (!Array.isArray(info.weights) || !Array.isArray(info.biases) || info.weights.length !== sizes.length - 1)
    throw new Error(`info.json must list weights and biases for ${sizes.length - 1} layers`);
  const layers = [];
  for (let i = 0; i < sizes.length - 1; i++) {
    const rows = i === sizes.length - 2 ? sizes[i + 1] : pad4(sizes[i + 1]), cols = pad4(sizes[i]);
    if ((info.weights[i] || []).length !== rows * cols || (info.biases[i] || []).length !== rows)
      throw new Error(`weights[${i}] must hold ${rows} x ${cols} numbers and biases[${i}] ${rows}`);
    layers.push({ rows, cols, w: Float32Array.from(info.weights[i]), b: Float32Array.from(info.biases[i]) });
  }
  const expectedIn = info.planes + (decoder === "light" ? (order === 0 ? 2 : order * order - 1) : 0);
  const expectedOut = decoder === "light" ? 3 : 3 * order * order;
  if (sizes[0] !== expectedIn || sizes[sizes.length - 1] !== expectedOut)
    throw new Error(`a ${decoder} decoder of ${info.planes} codes runs from ${expectedIn} inputs to ${expectedOut} ` +
                    `outputs, found ${sizes[0]} to ${sizes[sizes.length - 1]}`);
  return { decoder, order, codes: info.planes, layers };
}

// The light's uniforms: the first layer's bias and the last layer's 3 rows of weights and its bias.
function neuralLightUniforms(net, l) {
  const first = net.layers[0], last = net.layers[net.layers.length - 1];
  const bias0 = Float32Array.from(first.b);
  if (net.decoder === "light") {
    const feats = net.order === 0 ? [l[0], l[1]] : Array.from(realSh(net.order, l)).slice(1);
    for (let o = 0; o < first.rows; o++)
      for (let f = 0; f < feats.length; f++) bias0[o] += first.w[o * first.cols + net.codes + f] * feats[f];
    return { bias0, last: last.w, lastBias: last.b };
  }
  const y = realSh(net.order, l).map((v) => v * Math.sqrt(4 * Math.PI));   // the constant harmonic is 1
  const weights = new Float32Array(3 * last.cols), bias = new Float32Array(3);
  for (let p = 0; p < y.length; p++)
    for (let c = 0; c < 3; c++) {
      const row = 3 * p + c;   // the decoder's outputs are (coefficient, channel)
      bias[c] += y[p] * last.b[row];
      for (let j = 0; j < last.cols; j++) weights[c * last.cols + j] += y[p] * last.w[row * last.cols + j];
    }
  return { bias0, last: weights, lastBias: bias };
}

// Every layer but the last as RGBA texels, one row per output unit; returns {data, width, height, offsets}.
function neuralTexture(net) {
  const stored = net.layers.slice(0, -1), width = Math.max(...stored.map((layer) => layer.cols / 4));
  const offsets = [];
  let height = 0;
  for (const layer of stored) { offsets.push(height); height += layer.rows; }
  const data = new Float32Array(width * height * 4);
  stored.forEach((layer, i) => {
    for (let r = 0; r < layer.rows; r++)
      data.set(layer.w.subarray(r * layer.cols, (r + 1) * layer.cols), (offsets[i] + r) * width * 4);
  });
  return { data, width, height, offsets };
}

// GLSL ES 1.0 source evaluating the network (every loop bound a constant; arrays indexed by loop indices).
function neuralSource(net, texture) {
  const k4 = Math.ceil(net.codes / 4), images = Math.ceil(net.codes / 3), n = net.layers.length;
  let src = "precision highp float;\nvarying vec2 v_uv;\nuniform sampler2D u_net;\nuniform vec2 u_netSize;\n";
  for (let j = 0; j < images; j++) src += `uniform sampler2D u_plane${j};\n`;
  src += `uniform float u_low[${net.codes}], u_span[${net.codes}];\n`;
  net.layers.slice(0, -1).forEach((layer, i) => { src += `uniform vec4 u_b${i}[${layer.rows / 4}];\n`; });
  const c4 = net.layers[n - 1].cols / 4;
  src += `uniform vec4 u_last[${3 * c4}];\nuniform vec3 u_lastBias;\n`;
  src += "vec4 elu(vec4 x) { return max(x, 0.0) + exp(min(x, 0.0)) - 1.0; }\n";
  src += "vec4 w(float row, float col) { return texture2D(u_net, (vec2(col, row) + 0.5) / u_netSize); }\n";
  src += `void main() {\n  vec4 h0[${k4}];\n  vec3 t;\n`;
  for (let j = 0; j < k4; j++) src += `  h0[${j}] = vec4(0.0);\n`;
  for (let j = 0; j < images; j++) {
    src += `  t = texture2D(u_plane${j}, v_uv).rgb;\n`;
    for (let c = 0; c < 3 && 3 * j + c < net.codes; c++) {
      const k = 3 * j + c;
      src += `  h0[${Math.floor(k / 4)}][${k % 4}] = t[${c}] * u_span[${k}] + u_low[${k}];\n`;
    }
  }
  net.layers.slice(0, -1).forEach((layer, i) => {
    const in4 = i === 0 ? k4 : layer.cols / 4, out4 = layer.rows / 4;   // layer 0 reads the codes' columns only
    src += `  vec4 h${i + 1}[${out4}];\n  for (int o = 0; o < ${out4}; o++) {\n    vec4 s = u_b${i}[o];\n` +
           `    float row = float(${texture.offsets[i]} + 4 * o);\n    for (int j = 0; j < ${in4}; j++) {\n` +
           `      vec4 x = h${i}[j];\n      float col = float(j);\n` +
           "      s += vec4(dot(x, w(row, col)), dot(x, w(row + 1.0, col)), dot(x, w(row + 2.0, col)), " +
           "dot(x, w(row + 3.0, col)));\n    }\n" + `    h${i + 1}[o] = elu(s);\n  }\n`;
  });
  src += `  vec3 rgb = u_lastBias;\n  for (int j = 0; j < ${c4}; j++) {\n    vec4 x = h${n - 1}[j];\n` +
         `    rgb += vec3(dot(x, u_last[j]), dot(x, u_last[${c4} + j]), dot(x, u_last[${2 * c4} + j]));\n  }\n`;
  src += "  gl_FragColor = vec4(clamp(rgb, 0.0, 1.0), 1.0);\n}\n";
  return src;
}

// Checks the layout, builds the network texture (float: OES_texture_float) and returns the fragment source.
function neuralPrepare(gl, info) {
  for (const key of ["planes", "samples", "min", "max", "weights", "biases"])
    if (info[key] === undefined) throw new Error(`a neural info.json needs '${key}'`);
  if (!gl.getExtension("OES_texture_float")) throw new Error("this browser's WebGL has no float textures");
  const net = neuralNetwork(info), texture = neuralTexture(net);
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, tex);
  gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA, texture.width, texture.height, 0, gl.RGBA, gl.FLOAT, texture.data);
  for (const [key, value] of [[gl.TEXTURE_MIN_FILTER, gl.NEAREST], [gl.TEXTURE_MAG_FILTER, gl.NEAREST],
                              [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE]])
    gl.texParameteri(gl.TEXTURE_2D, key, value);
  const low = info.min.flat().slice(0, net.codes), high = info.max.flat().slice(0, net.codes);
  info._neural = { net, texture, tex, low, span: high.map((v, k) => v - low[k]) };
  return neuralSource(net, texture);
}

// Sets the network's uniforms for the light l and binds its texture to unit `unit`.
function neuralUniforms(gl, prog, info, l, unit) {
  const { net, texture, tex, low, span } = info._neural, light = neuralLightUniforms(net, l);
  const loc = (name) => gl.getUniformLocation(prog, name);
  gl.uniform1fv(loc("u_low[0]"), new Float32Array(low));
  gl.uniform1fv(loc("u_span[0]"), new Float32Array(span));
  gl.uniform4fv(loc("u_b0[0]"), light.bias0);
  net.layers.slice(1, -1).forEach((layer, i) => gl.uniform4fv(loc(`u_b${i + 1}[0]`), layer.b));
  gl.uniform4fv(loc("u_last[0]"), light.last);
  gl.uniform3fv(loc("u_lastBias"), light.lastBias);
  gl.uniform2f(loc("u_netSize"), texture.width, texture.height);
  gl.activeTexture(gl.TEXTURE0 + unit);
  gl.bindTexture(gl.TEXTURE_2D, tex);
  gl.uniform1i(loc("u_net"), unit);
}
