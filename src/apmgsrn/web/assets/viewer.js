// apmgsrn web viewer: ray-marches a neural field in WebGL2, the way `apmgsrn render` does on the CPU.
// The model (feature tables, grid placements, decoder weights) is embedded in this page; nothing is fetched.
"use strict";
(() => {
  const TABLE_WIDTH_SHIFT = 12; // the feature table texture is 4096 texels wide
  const TABLE_WIDTH = 1 << TABLE_WIDTH_SHIFT;
  const TRANSFER_SIZE = 4096; // entries of the baked transfer function, as RendererConfig.table_size
  const TRANSFER_SIDE = 64; // stored as a 64 x 64 texture
  const HASH_PRIMES = [1, 2654435761, 805459861];

  const $ = (id) => document.getElementById(id);
  const readJson = (id) => JSON.parse($(id).textContent);
  const scene = readJson("apm-scene");
  const colormaps = readJson("apm-colormaps");
  const settings = readJson("apm-settings");

  // ------------------------------------------------------------------ arrays: base64 -> inflate -> float32
  function base64Bytes(text) {
    const binary = atob(text);
    const out = new Uint8Array(binary.length);
    for (let i = 0; i < binary.length; i++) out[i] = binary.charCodeAt(i);
    return out;
  }

  async function inflate(text) {
    const stream = new Blob([base64Bytes(text)]).stream().pipeThrough(new DecompressionStream("deflate"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  }

  function halfToFloat(h) {
    const sign = h & 0x8000 ? -1 : 1;
    const exponent = (h >> 10) & 0x1f;
    const fraction = h & 0x3ff;
    if (exponent === 0) return sign * fraction * 2 ** -24;
    if (exponent === 31) return fraction ? NaN : sign * Infinity;
    return sign * (1 + fraction / 1024) * 2 ** (exponent - 15);
  }

  // A blob's values as float32, exactly as the Python loader computes them.
  async function decodeBlob(key) {
    const entry = scene.blobs[key];
    const bytes = await inflate(entry.data);
    const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    const n = entry.count;
    const out = new Float32Array(n);
    if (entry.encoding === "float32") {
      if (bytes.length !== 4 * n) throw new Error(`array ${key}: ${bytes.length} bytes, expected ${4 * n}`);
      for (let i = 0; i < n; i++) out[i] = view.getFloat32(4 * i, true);
    } else if (entry.encoding === "float16") {
      if (bytes.length !== 2 * n) throw new Error(`array ${key}: ${bytes.length} bytes, expected ${2 * n}`);
      for (let i = 0; i < n; i++) out[i] = halfToFloat(view.getUint16(2 * i, true));
    } else if (entry.encoding === "quantized") {
      const width = entry.width, group = entry.group, groups = entry.groups;
      if (bytes.length !== width * n + 2 * groups) throw new Error(`array ${key}: wrong length`);
      const steps = new Float64Array(groups);
      for (let g = 0; g < groups; g++) steps[g] = halfToFloat(view.getUint16(width * n + 2 * g, true));
      for (let i = 0; i < n; i++) {
        let z = 0;
        for (let k = 0; k < width; k++) z += bytes[k * n + i] * 2 ** (8 * k);
        const level = z % 2 === 0 ? z / 2 : -(z + 1) / 2; // zigzag
        out[i] = Math.fround(level * steps[Math.floor(i / group)]); // float32 product, as numpy's
      }
    } else {
      throw new Error(`array ${key}: unknown encoding ${entry.encoding}`);
    }
    return out;
  }

  // ------------------------------------------------------------------ WebGL2 setup
  const canvas = $("apm-canvas");
  const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true, alpha: false });
  const field = scene.field;
  const levels = field.levels;
  const decoderSizes = field.decoder; // [in, width, ..., 1]
  const encoderOut = levels.reduce((sum, level) => sum + level.features, 0) + 6 * field.fourier;

  function texture(internal, format, type, width, height, data) {
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, width, height, 0, format, type, data);
    return tex;
  }

  // The decoder's layers as one RGBA32F texture: output o of layer l is row rowBase[l] + o, four inputs a texel.
  function decoderLayout() {
    const layers = [];
    let rows = 0, width = 1;
    for (let l = 0; l + 1 < decoderSizes.length; l++) {
      const inputs = decoderSizes[l], outputs = decoderSizes[l + 1];
      const in4 = Math.ceil(inputs / 4), out4 = Math.ceil(outputs / 4);
      layers.push({ inputs, outputs, in4, out4, rowBase: rows });
      rows += 4 * out4;
      width = Math.max(width, in4);
    }
    return { layers, rows, width };
  }
  const weightLayout = decoderLayout();

  function weightTexels(weights) {
    const { layers, rows, width } = weightLayout;
    const texels = new Float32Array(rows * width * 4);
    layers.forEach((layer, l) => {
      const w = weights[l]; // [outputs, inputs] row-major
      if (w.length !== layer.outputs * layer.inputs) throw new Error(`decoder layer ${l}: wrong size`);
      for (let o = 0; o < layer.outputs; o++) {
        for (let i = 0; i < layer.inputs; i++) {
          texels[((layer.rowBase + o) * width + (i >> 2)) * 4 + (i & 3)] = w[o * layer.inputs + i];
        }
      }
    });
    return texels;
  }

  // ------------------------------------------------------------------ the shader
  // A decoder weight texel (four inputs of one output). Measured in the software renderer: reading them from
  // uniform arrays instead is no faster (docs/web.md), and a texture holds a decoder of any size.
  const weightAt = (row) => `texelFetch(uWeights, ivec2(j, ${row}), 0)`;

  function fragmentSource() {
    const inPad = 4 * Math.ceil(encoderOut / 4);
    const lines = [];
    const { layers } = weightLayout;
    // The decoder, layer by layer, with its sizes as constants.
    lines.push(`float decode() {`);
    lines.push(`  vec4 h0[${inPad / 4}];`);
    lines.push(`  for (int j = 0; j < ${inPad / 4}; j++) h0[j] = vec4(feat[4 * j], feat[4 * j + 1], feat[4 * j + 2], feat[4 * j + 3]);`);
    layers.forEach((layer, l) => {
      const last = l === layers.length - 1;
      lines.push(`  vec4 h${l + 1}[${layer.out4}];`);
      lines.push(`  for (int o = 0; o < ${layer.out4}; o++) {`);
      lines.push(`    vec4 s = vec4(0.0); int r = ${layer.rowBase} + 4 * o;`);
      lines.push(`    for (int j = 0; j < ${layer.in4}; j++) {`);
      lines.push(`      vec4 x = h${l}[j];`);
      for (const [lane, k] of [["x", 0], ["y", 1], ["z", 2], ["w", 3]]) {
        lines.push(`      s.${lane} += dot(${weightAt(`r + ${k}`)}, x);`);
      }
      lines.push(`    }`);
      lines.push(`    h${l + 1}[o] = ${last ? "s" : "max(s, vec4(0.0))"};`);
      lines.push(`  }`);
    });
    lines.push(`  return h${layers.length}[0].x;`);
    lines.push(`}`);
    const fourier = field.fourier;
    return `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
#define NL ${levels.length}
#define IN_PAD ${inPad}
uniform sampler2D uTable;
uniform sampler2D uWeights;
uniform sampler2D uTransfer;
uniform vec4 uMaps[3 * NL];
uniform ivec4 uRes[NL];      // vertices x, y, z; features
uniform ivec4 uAddr[NL];     // offset, row stride, feature stride, table rows
uniform ivec2 uKind[NL];     // flags (1 hashed, 2 unbounded); first output column
uniform vec3 uEye, uForward, uRight, uUp;
uniform vec2 uHalf, uSize;
uniform vec3 uExtent, uBackground;
uniform float uStep, uRefStep, uEarly;
uniform vec3 uTfRange;       // min, max, (entries - 1) / (max - min)
uniform vec2 uFit;
uniform vec4 uTransform;     // kind (0 none, 1 log10, 2 zscore), offset, mean, std
uniform vec2 uConstant;      // (1: a constant volume, its value)
out vec4 outColor;
float feat[IN_PAD];

float tableAt(int i) { return texelFetch(uTable, ivec2(i & ${TABLE_WIDTH - 1}, i >> ${TABLE_WIDTH_SHIFT}), 0).r; }

void encode(vec3 p) {
  for (int j = 0; j < IN_PAD; j++) feat[j] = 0.0;
  for (int l = 0; l < NL; l++) {
    vec4 r0 = uMaps[3 * l], r1 = uMaps[3 * l + 1], r2 = uMaps[3 * l + 2];
    vec3 f = vec3(dot(r0.xyz, p) + r0.w, dot(r1.xyz, p) + r1.w, dot(r2.xyz, p) + r2.w);
    ivec3 res = uRes[l].xyz;
    int features = uRes[l].w;
    int flags = uKind[l].x, col = uKind[l].y;
    bool bounded = (flags & 2) == 0;
    if (bounded && (any(lessThanEqual(f, vec3(-1.0))) || any(greaterThanEqual(f, vec3(res))))) continue;
    vec3 lower = floor(f);
    vec3 w1 = f - lower, w0 = 1.0 - w1;
    ivec3 base = ivec3(lower);
    int size = uAddr[l].w;
    for (int k = 0; k < 8; k++) {
      ivec3 o = ivec3(k & 1, (k >> 1) & 1, k >> 2);
      ivec3 v = base + o;
      if (bounded && (any(lessThan(v, ivec3(0))) || any(greaterThanEqual(v, res)))) continue;
      float w = (o.x == 1 ? w1.x : w0.x) * (o.y == 1 ? w1.y : w0.y) * (o.z == 1 ? w1.z : w0.z);
      int row;
      if ((flags & 1) != 0) {
        uvec3 u = uvec3(v);
        row = int((u.x * ${HASH_PRIMES[0]}u ^ u.y * ${HASH_PRIMES[1]}u ^ u.z * ${HASH_PRIMES[2]}u) & uint(size - 1));
      } else {
        row = v.x + res.x * (v.y + res.y * v.z);
        if (!bounded) row = row % size;
      }
      int at = uAddr[l].x + row * uAddr[l].y;
      for (int c = 0; c < features; c++) feat[col + c] += w * tableAt(at + c * uAddr[l].z);
    }
  }
${fourier > 0 ? `  int fc = ${encoderOut - 6 * fourier};
  for (int a = 0; a < 3; a++) for (int k = 0; k < ${fourier}; k++) {
    float angle = p[a] * (3.14159265358979 * exp2(float(k)));
    feat[fc + a * ${fourier} + k] = sin(angle);
    feat[fc + ${3 * fourier} + a * ${fourier} + k] = cos(angle);
  }` : ""}
}

${lines.join("\n")}

float fieldValue(vec3 p) {
  if (uConstant.x > 0.5) return uConstant.y;
  encode(p);
  float fitted = decode() * (uFit.y - uFit.x) + uFit.x;
  if (uTransform.x == 1.0) return pow(10.0, fitted) - uTransform.y;
  if (uTransform.x == 2.0) return fitted * uTransform.w + uTransform.z;
  return fitted;
}

vec4 transferEntry(int i) { return texelFetch(uTransfer, ivec2(i & ${TRANSFER_SIDE - 1}, i >> 6), 0); }

vec4 transfer(float v) {
  if (isnan(v)) return vec4(0.0);
  float position = clamp((v - uTfRange.x) * uTfRange.z, 0.0, ${TRANSFER_SIZE - 1}.0);
  int low = min(int(position), ${TRANSFER_SIZE - 2});
  return mix(transferEntry(low), transferEntry(low + 1), position - float(low));
}

void main() {
  vec2 pixel = gl_FragCoord.xy;
  float u = (pixel.x / uSize.x * 2.0 - 1.0) * uHalf.x;
  float v = (pixel.y / uSize.y * 2.0 - 1.0) * uHalf.y;
  vec3 dir = normalize(uForward + u * uRight + v * uUp);
  vec3 inverse = 1.0 / dir;
  vec3 t0 = (-uExtent - uEye) * inverse, t1 = (uExtent - uEye) * inverse;
  vec3 small = min(t0, t1), large = max(t0, t1);
  float tNear = max(max(max(small.x, small.y), small.z), 0.0);
  float tFar = min(min(large.x, large.y), large.z);
  float len = max(tFar - tNear, 0.0);
  int count = int(max(ceil(len / uStep - 0.5), 0.0));
  vec3 origin = uEye / uExtent, direction = dir / uExtent;
  vec3 color = vec3(0.0);
  float transmittance = 1.0;
  for (int i = 0; i < count; i++) {
    if (transmittance < uEarly) break;
    float t = tNear + (float(i) + 0.5) * uStep;
    float low = i == 0 ? tNear : t - 0.5 * uStep;
    float high = i == count - 1 ? tFar : t + 0.5 * uStep;
    float exponent = max(high - low, 0.0) / uRefStep;
    vec4 rgba = transfer(fieldValue(origin + t * direction));
    if (rgba.a <= 0.0 || exponent <= 0.0) continue;
    float alpha = rgba.a >= 1.0 ? 1.0 : 1.0 - pow(1.0 - rgba.a, exponent);
    color += transmittance * alpha * rgba.rgb;
    transmittance *= 1.0 - alpha;
  }
  outColor = vec4(color + transmittance * uBackground, 1.0);
}
`;
  }

  const vertexSource = `#version 300 es
in vec2 aPosition;
void main() { gl_Position = vec4(aPosition, 0.0, 1.0); }
`;

  function compile(type, source) {
    const shader = gl.createShader(type);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
      throw new Error(`shader: ${gl.getShaderInfoLog(shader)}`);
    }
    return shader;
  }

  function program() {
    const p = gl.createProgram();
    gl.attachShader(p, compile(gl.VERTEX_SHADER, vertexSource));
    gl.attachShader(p, compile(gl.FRAGMENT_SHADER, fragmentSource()));
    gl.bindAttribLocation(p, 0, "aPosition");
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`program: ${gl.getProgramInfoLog(p)}`);
    return p;
  }

  // ------------------------------------------------------------------ camera (rendering/camera.py)
  const radians = (d) => (d * Math.PI) / 180;
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const unit = (a) => { const n = Math.hypot(a[0], a[1], a[2]); return [a[0] / n, a[1] / n, a[2] / n]; };

  function fitDistance(fov, width, height, extent) {
    const radius = Math.hypot(extent[0], extent[1], extent[2]);
    const halfNarrow = Math.atan(Math.tan(radians(fov) / 2) * Math.min(1, width / height));
    return (0.9 * radius) / Math.sin(halfNarrow);
  }

  function cameraOf(view, width, height) {
    const distance = view.distance ?? fitDistance(view.fov, width, height, scene.extent);
    const az = radians(view.azimuth), el = radians(view.elevation);
    const eye = [distance * Math.cos(el) * Math.sin(az), -distance * Math.cos(el) * Math.cos(az), distance * Math.sin(el)];
    let up = [0, 0, 1];
    if (Math.abs(Math.cos(el)) < 1e-6) {
      const s = Math.sign(el) || 1;
      up = [-Math.sin(az) * s, Math.cos(az) * s, 0];
    }
    const forward = unit(sub([0, 0, 0], eye));
    const right = unit(cross(forward, up));
    const trueUp = cross(right, forward);
    const halfHeight = Math.tan(radians(view.fov) / 2);
    return { eye, forward, right, up: trueUp, half: [halfHeight * width / height, halfHeight] };
  }

  // ------------------------------------------------------------------ transfer function (rendering/transfer_function.py)
  const colormapTables = {};

  async function loadColormaps() {
    const bytes = await inflate(colormaps.data);
    const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    const entries = colormaps.entries;
    colormaps.names.forEach((name, m) => {
      const table = new Float32Array(entries * 3);
      for (let i = 0; i < entries * 3; i++) table[i] = view.getUint16(2 * (m * entries * 3 + i), true) / 65535;
      colormapTables[name] = table;
    });
  }

  // Colour at a position in [0, 1] of the range: the baked map's entries interpolated linearly.
  function colorAt(table, x) {
    const n = table.length / 3;
    const position = Math.min(Math.max(x, 0), 1) * (n - 1);
    const low = Math.min(Math.floor(position), n - 2);
    const frac = position - low;
    return [0, 1, 2].map((c) => table[3 * low + c] * (1 - frac) + table[3 * (low + 1) + c] * frac);
  }

  // Opacity at a position in [0, 1]: linear between nodes, the end nodes' beyond them (OpacityMap, midpoint
  // 0.5 and sharpness 0).
  function opacityAt(points, x) {
    if (x <= points[0][0]) return points[0][1];
    for (let k = 1; k < points.length; k++) {
      if (x <= points[k][0]) {
        const [x0, a0] = points[k - 1], [x1, a1] = points[k];
        return x1 > x0 ? a0 + ((x - x0) / (x1 - x0)) * (a1 - a0) : a1;
      }
    }
    return points[points.length - 1][1];
  }

  function transferTexels(state) {
    const table = colormapTables[state.colormap];
    const texels = new Float32Array(TRANSFER_SIZE * 4);
    for (let i = 0; i < TRANSFER_SIZE; i++) {
      const x = i / (TRANSFER_SIZE - 1);
      const [r, g, b] = colorAt(table, x);
      texels.set([r, g, b, Math.min(Math.max(opacityAt(state.opacity, x), 0), 1)], 4 * i);
    }
    return texels;
  }

  // ------------------------------------------------------------------ state and drawing
  const state = {
    view: { ...settings.view },
    colormap: settings.colormap,
    opacity: settings.opacity.map((p) => [...p]),
    range: [...(settings.range ?? scene.value_range)],
    spp: settings.samples_per_ray,
    step: 0,
    width: settings.width,
    height: settings.height,
  };
  let prog = null, tableTex = null, weightTex = null, transferTex = null;
  const uniforms = {};
  const stepCache = new Map();

  async function stepData(index) {
    if (!stepCache.has(index)) {
      const step = scene.steps[index];
      stepCache.clear(); // one step's tables at a time
      const promise = (async () => {
        const parts = await Promise.all(step.table.map(decodeBlob));
        const weights = await Promise.all(step.decoder.map(decodeBlob));
        return { parts, weights, maps: step.maps };
      })();
      stepCache.set(index, promise);
    }
    return stepCache.get(index);
  }

  async function uploadStep(index) {
    const { parts, weights, maps } = await stepData(index);
    const total = parts.reduce((sum, p) => sum + p.length, 0);
    const rows = Math.max(1, Math.ceil(total / TABLE_WIDTH));
    if (rows > gl.getParameter(gl.MAX_TEXTURE_SIZE)) throw new Error(`the feature table (${total} values) is larger than this GPU's textures`);
    const flat = new Float32Array(rows * TABLE_WIDTH);
    let at = 0;
    for (const part of parts) { flat.set(part, at); at += part.length; }
    if (tableTex) gl.deleteTexture(tableTex);
    if (weightTex) gl.deleteTexture(weightTex);
    gl.activeTexture(gl.TEXTURE0);
    tableTex = texture(gl.R32F, gl.RED, gl.FLOAT, TABLE_WIDTH, rows, flat);
    gl.activeTexture(gl.TEXTURE1);
    weightTex = texture(gl.RGBA32F, gl.RGBA, gl.FLOAT, weightLayout.width, weightLayout.rows, weightTexels(weights));
    gl.useProgram(prog);
    gl.uniform4fv(uniforms.uMaps, new Float32Array(maps.flat()));
    state.step = index;
  }

  function uploadTransfer() {
    if (transferTex) gl.deleteTexture(transferTex);
    gl.activeTexture(gl.TEXTURE2);
    transferTex = texture(gl.RGBA32F, gl.RGBA, gl.FLOAT, TRANSFER_SIDE, TRANSFER_SIDE, transferTexels(state));
  }

  function setStaticUniforms() {
    gl.useProgram(prog);
    const res = [], addr = [], kind = [];
    let column = 0;
    for (const level of levels) {
      res.push(...level.res, level.features);
      addr.push(level.offset, level.row_stride, level.feature_stride, level.size);
      kind.push((level.hashed ? 1 : 0) | (level.bounded ? 0 : 2), column);
      column += level.features;
    }
    gl.uniform4iv(uniforms.uRes, new Int32Array(res));
    gl.uniform4iv(uniforms.uAddr, new Int32Array(addr));
    gl.uniform2iv(uniforms.uKind, new Int32Array(kind));
    gl.uniform1i(uniforms.uTable, 0);
    gl.uniform1i(uniforms.uWeights, 1);
    gl.uniform1i(uniforms.uTransfer, 2);
    gl.uniform3fv(uniforms.uExtent, scene.extent);
    gl.uniform3fv(uniforms.uBackground, settings.background);
    gl.uniform1f(uniforms.uEarly, settings.early_termination);
    gl.uniform2f(uniforms.uFit, field.fit[0], field.fit[1]);
    const kinds = { none: 0, log10: 1, zscore: 2 };
    const t = field.transform;
    gl.uniform4f(uniforms.uTransform, kinds[t.kind], t.offset, t.mean, t.std);
    gl.uniform2f(uniforms.uConstant, field.constant ? 1 : 0, field.value_min);
  }

  function setFrameUniforms() {
    const camera = cameraOf(state.view, state.width, state.height);
    const longest = 2 * Math.max(...scene.extent);
    gl.uniform3fv(uniforms.uEye, camera.eye);
    gl.uniform3fv(uniforms.uForward, camera.forward);
    gl.uniform3fv(uniforms.uRight, camera.right);
    gl.uniform3fv(uniforms.uUp, camera.up);
    gl.uniform2fv(uniforms.uHalf, camera.half);
    gl.uniform2f(uniforms.uSize, state.width, state.height);
    gl.uniform1f(uniforms.uStep, longest / state.spp);
    gl.uniform1f(uniforms.uRefStep, longest / settings.reference_samples);
    let [lo, hi] = state.range;
    if (!(hi > lo)) hi = lo + 1;
    gl.uniform3f(uniforms.uTfRange, lo, hi, (TRANSFER_SIZE - 1) / (hi - lo));
  }

  // One frame, drawn in strips of rows (each a separate draw the GPU finishes before the next), so a slow
  // software renderer shows progress and never holds the GPU for long. Resolves with the frame time in ms.
  let generation = 0;
  let stripRows = 32;
  function drawFrame() {
    const mine = ++generation;
    const started = performance.now();
    if (canvas.width !== state.width || canvas.height !== state.height) {
      canvas.width = state.width;
      canvas.height = state.height;
    }
    gl.viewport(0, 0, state.width, state.height);
    gl.useProgram(prog);
    setFrameUniforms();
    gl.enable(gl.SCISSOR_TEST);
    const probe = new Uint8Array(4);
    return new Promise((resolve) => {
      let row = state.height;
      const next = () => {
        if (mine !== generation) { resolve(null); return; }
        const t0 = performance.now();
        const rows = Math.min(stripRows, row);
        row -= rows; // top strip first (GL rows count from the bottom)
        gl.scissor(0, row, state.width, rows);
        gl.drawArrays(gl.TRIANGLES, 0, 3);
        gl.readPixels(0, row, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, probe); // waits for the strip
        const spent = performance.now() - t0;
        stripRows = Math.max(1, Math.min(state.height, Math.round(stripRows * Math.min(2, Math.max(0.5, 40 / Math.max(spent, 1))))));
        if (row > 0) { $("apm-status").textContent = `rendering... ${Math.round(100 * (1 - row / state.height))}%`; setTimeout(next, 0); return; }
        const ms = performance.now() - started;
        $("apm-status").textContent = "";
        $("apm-frame").textContent = `frame time: ${ms.toFixed(0)} ms (${(1000 / ms).toFixed(1)} frames/s) at ${state.width}x${state.height}, ${state.spp} samples per ray`;
        canvas.dataset.frames = String(Number(canvas.dataset.frames || 0) + 1);
        resolve(ms);
      };
      next();
    });
  }

  let pending = null;
  function requestFrame() {
    if (pending) return pending;
    pending = new Promise((resolve) => requestAnimationFrame(() => { pending = null; drawFrame().then(resolve); }));
    return pending;
  }

  // ------------------------------------------------------------------ controls
  function setupControls() {
    const select = $("apm-colormap");
    for (const name of colormaps.names) {
      const option = document.createElement("option");
      option.value = option.textContent = name;
      select.appendChild(option);
    }
    select.value = state.colormap;
    select.addEventListener("change", () => { state.colormap = select.value; uploadTransfer(); drawOpacity(); requestFrame(); });
    const [minInput, maxInput] = [$("apm-min"), $("apm-max")];
    const showRange = () => { minInput.value = String(state.range[0]); maxInput.value = String(state.range[1]); };
    showRange();
    const readRange = () => {
      const lo = Number(minInput.value), hi = Number(maxInput.value);
      if (Number.isFinite(lo) && Number.isFinite(hi) && hi > lo) { state.range = [lo, hi]; requestFrame(); }
    };
    minInput.addEventListener("change", readRange);
    maxInput.addEventListener("change", readRange);
    $("apm-range-reset").addEventListener("click", () => { state.range = [...scene.value_range]; showRange(); requestFrame(); });
    const spp = $("apm-spp");
    spp.value = String(state.spp);
    spp.addEventListener("change", () => {
      const n = Math.round(Number(spp.value));
      if (n >= 8 && n <= 4096) { state.spp = n; requestFrame(); }
    });
    $("apm-view-reset").addEventListener("click", () => { state.view = { ...settings.view }; requestFrame(); });

    // Orbit and zoom.
    let drag = null;
    canvas.addEventListener("pointerdown", (e) => { drag = { x: e.clientX, y: e.clientY, view: { ...state.view } }; canvas.setPointerCapture(e.pointerId); });
    canvas.addEventListener("pointermove", (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      state.view.azimuth = drag.view.azimuth - dx * 0.4;
      state.view.elevation = Math.max(-89.9, Math.min(89.9, drag.view.elevation + dy * 0.4));
      requestFrame();
    });
    canvas.addEventListener("pointerup", () => { drag = null; });
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      const current = state.view.distance ?? fitDistance(state.view.fov, state.width, state.height, scene.extent);
      state.view.distance = Math.max(0.05, current * Math.exp(e.deltaY * 0.001));
      requestFrame();
    }, { passive: false });

    // Time steps.
    if (scene.series) {
      $("apm-time-box").hidden = false;
      const slider = $("apm-time");
      slider.max = String(scene.steps.length - 1);
      const label = () => { $("apm-time-label").textContent = `step ${state.step} of ${scene.steps.length} (number ${scene.steps[state.step].label})`; };
      label();
      slider.addEventListener("input", async () => { await setStep(Number(slider.value)); label(); });
    }
    setupOpacityEditor();
  }

  // The opacity editor: nodes (position in [0, 1] of the range, opacity) over the colour map.
  const editor = $("apm-opacity");
  function drawOpacity() {
    const ctx = editor.getContext("2d");
    const w = editor.width, h = editor.height;
    const table = colormapTables[state.colormap];
    for (let x = 0; x < w; x++) {
      const [r, g, b] = colorAt(table, x / (w - 1));
      ctx.fillStyle = `rgb(${Math.round(255 * r)},${Math.round(255 * g)},${Math.round(255 * b)})`;
      ctx.fillRect(x, h - 10, 1, 10);
    }
    ctx.clearRect(0, 0, w, h - 10);
    ctx.strokeStyle = "#222";
    ctx.beginPath();
    state.opacity.forEach(([x, a], k) => { const px = x * (w - 1), py = (1 - a) * (h - 14) + 2; if (k) ctx.lineTo(px, py); else ctx.moveTo(px, py); });
    ctx.stroke();
    ctx.fillStyle = "#222";
    for (const [x, a] of state.opacity) ctx.fillRect(x * (w - 1) - 3, (1 - a) * (h - 14) + 2 - 3, 6, 6);
  }
  function setupOpacityEditor() {
    const w = editor.width, h = editor.height;
    const at = (e) => { const r = editor.getBoundingClientRect(); return [Math.min(1, Math.max(0, (e.clientX - r.left) / (w - 1))), Math.min(1, Math.max(0, 1 - (e.clientY - r.top - 2) / (h - 14)))]; };
    const nearest = (p) => {
      let best = -1, distance = 0.05;
      state.opacity.forEach(([x, a], k) => { const d = Math.hypot(x - p[0], (a - p[1]) * 0.5); if (d < distance) { distance = d; best = k; } });
      return best;
    };
    let moving = -1;
    editor.addEventListener("pointerdown", (e) => {
      const p = at(e);
      moving = nearest(p);
      if (moving < 0) {
        state.opacity.push(p);
        state.opacity.sort((a, b) => a[0] - b[0]);
        moving = state.opacity.indexOf(p);
        changed();
      }
      editor.setPointerCapture(e.pointerId);
    });
    editor.addEventListener("pointermove", (e) => {
      if (moving < 0) return;
      const p = at(e), k = moving, n = state.opacity.length;
      const lo = k === 0 ? 0 : state.opacity[k - 1][0], hi = k === n - 1 ? 1 : state.opacity[k + 1][0];
      state.opacity[k] = [Math.min(hi, Math.max(lo, p[0])), p[1]];
      changed();
    });
    editor.addEventListener("pointerup", () => { moving = -1; });
    editor.addEventListener("dblclick", (e) => {
      const k = nearest(at(e));
      if (k >= 0 && state.opacity.length > 2) { state.opacity.splice(k, 1); changed(); }
    });
    const changed = () => { drawOpacity(); uploadTransfer(); requestFrame(); };
    drawOpacity();
  }

  async function setStep(index) {
    if (!(index >= 0 && index < scene.steps.length)) throw new Error(`step ${index} is outside the series`);
    await uploadStep(index);
    return requestFrame();
  }

  // ------------------------------------------------------------------ start
  async function start() {
    if (!gl) throw new Error("this browser has no WebGL2");
    const loadStart = performance.now();
    $("apm-title").textContent = scene.name;
    $("apm-about").textContent = scene.about;
    for (const note of scene.notes) { const li = document.createElement("li"); li.textContent = note; $("apm-notes").appendChild(li); }
    prog = program();
    const count = gl.getProgramParameter(prog, gl.ACTIVE_UNIFORMS);
    for (let i = 0; i < count; i++) {
      const name = gl.getActiveUniform(prog, i).name.replace(/\[0\]$/, "");
      uniforms[name] = gl.getUniformLocation(prog, name);
    }
    const buffer = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 3, -1, -1, 3]), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    await loadColormaps();
    setStaticUniforms();
    await uploadStep(0);
    uploadTransfer();
    setupControls();
    const loadMs = performance.now() - loadStart;
    const frameMs = await drawFrame();
    api.loadMs = loadMs;
    api.firstFrameMs = frameMs;
    return { loadMs, frameMs };
  }

  // For scripts and tests: the state, a way to set it and to wait for the frame it gives.
  const api = {
    state,
    async render(changes = {}) {
      if (changes.view) Object.assign(state.view, changes.view);
      for (const key of ["width", "height", "spp"]) if (changes[key] !== undefined) state[key] = changes[key];
      if (changes.range) state.range = [...changes.range];
      if (changes.colormap) state.colormap = changes.colormap;
      if (changes.opacity) state.opacity = changes.opacity.map((p) => [...p]);
      if (changes.colormap || changes.opacity) { uploadTransfer(); drawOpacity(); }
      if (changes.step !== undefined && changes.step !== state.step) await uploadStep(changes.step);
      return drawFrame();
    },
    snapshot() { return canvas.toDataURL("image/png"); },
  };
  window.apmgsrn = api;
  api.ready = start().catch((error) => {
    $("apm-status").textContent = `error: ${error.message}`;
    api.error = String(error.message);
    throw error;
  });
})();
