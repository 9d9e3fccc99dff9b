// reflectmm viewer: a morphable face reflectance model in WebGL2, shaded by the contract of docs/design.md §2.
// Data: the JSON bundle in <script id="reflectmm-data"> (format reflectmm.viewer/1, docs/viewer.md).
// State: the URL hash (docs/viewer.md, "State"), read at load and on every hashchange, written on every change.
(function () {
  'use strict';

  var DOC = JSON.parse(document.getElementById('reflectmm-data').textContent);
  var $ = function (id) { return document.getElementById(id); };

  // ------------------------------------------------------------------------------------------------ blobs
  var HALF = null;
  function halfTable() {  // float16 bit pattern -> float32, all 65536 values
    if (HALF) return HALF;
    HALF = new Float32Array(65536);
    for (var h = 0; h < 65536; h++) {
      var s = (h & 0x8000) ? -1 : 1, e = (h >> 10) & 0x1f, f = h & 0x3ff;
      HALF[h] = e === 0 ? s * Math.pow(2, -14) * (f / 1024) :
        e === 31 ? (f ? NaN : s * Infinity) : s * Math.pow(2, e - 15) * (1 + f / 1024);
    }
    return HALF;
  }
  function bytes(b64) {
    var bin = atob(b64), u = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) u[i] = bin.charCodeAt(i);
    return u;
  }
  // A blob record -> typed array (float32 for f4/f2/i1, uint16/uint32 for indices).
  function decode(rec) {
    var u = bytes(rec.data), buf = u.buffer;
    if (rec.dtype === 'f4') return new Float32Array(buf);
    if (rec.dtype === 'u2') return new Uint16Array(buf);
    if (rec.dtype === 'u4') return new Uint32Array(buf);
    if (rec.dtype === 'f2') {
      var t = halfTable(), h = new Uint16Array(buf), out = new Float32Array(h.length);
      for (var i = 0; i < h.length; i++) out[i] = t[h[i]];
      return out;
    }
    if (rec.dtype === 'i1') {  // (M, N, C) int8 with a scale per (M, C)
      var q = new Int8Array(buf), M = rec.shape[0], N = rec.shape[1], C = rec.shape[2];
      var o = new Float32Array(q.length);
      for (var m = 0; m < M; m++) for (var n = 0; n < N; n++) for (var c = 0; c < C; c++) {
        var k = (m * N + n) * C + c; o[k] = q[k] * rec.scale[m * C + c];
      }
      return o;
    }
    throw new Error('unknown blob dtype ' + rec.dtype);
  }

  // ------------------------------------------------------------------------------------------------ data
  var mesh = {
    pos: decode(DOC.mesh.positions), nrm: decode(DOC.mesh.normals), tri: decode(DOC.mesh.triangles),
  };
  mesh.n = mesh.pos.length / 3;
  var models = DOC.models.map(function (m) {
    return {
      name: m.name, K: m.exponents.length, M: m.sigma.length, sigma: m.sigma, exponents: m.exponents,
      am: decode(m.albedo_mean), wm: decode(m.weights_mean), ab: decode(m.albedo_basis), wb: decode(m.weights_basis),
    };
  });
  var SH = DOC.shading, ORDER = SH.order, NSH = (ORDER + 1) * (ORDER + 1);
  var envs = DOC.lights.envmaps.map(function (e) { return { name: e.name, sh: decode(e.sh), exposure: e.exposure }; });
  var lmodel = DOC.lights.model ? {
    order: DOC.lights.model.order, mean: decode(DOC.lights.model.mean), bases: decode(DOC.lights.model.bases),
    sigma: DOC.lights.model.sigma, level: DOC.lights.model.level, exposure: DOC.lights.model.exposure,
  } : null;
  var MAXC = Math.max.apply(null, models.map(function (m) { return m.M; }));
  var MAXK = Math.max.apply(null, models.map(function (m) { return m.K; }));
  var LC = lmodel ? lmodel.sigma.length : 0;

  // ------------------------------------------------------------------------------------------------ state
  var LAYERS = ['full', 'diffuse', 'specular'];
  for (var li = 0; li < MAXK; li++) LAYERS.push('lobe' + li);
  LAYERS.push('albedo', 'sumw');
  for (li = 0; li < MAXK; li++) LAYERS.push('weight' + li);

  function defaultLight() { return envs.length ? 'env:0' : (lmodel ? 'model' : 'point'); }
  function defaultState() {
    return {
      beta: new Array(MAXC).fill(0), light: defaultLight(), gamma: new Array(LC).fill(0), rot: 0,
      lp: [0, 0, DOC.camera.distance], li: null, cam: [0, 0, DOC.camera.distance], focal: null, size: null,
      layer: 'full', exposure: null, ev: 0, display: DOC.display['default'], ui: 1, aa: 1,
      split: models.length > 1 ? 1 : 0, model: 0,
    };
  }
  var S = defaultState();

  function nums(s) { return s.split(',').map(Number).filter(function (x) { return isFinite(x); }); }
  function parseHash(h) {
    var st = defaultState();
    (h || '').replace(/^#/, '').split('&').forEach(function (kv) {
      if (!kv) return;
      var i = kv.indexOf('='), k = i < 0 ? kv : kv.slice(0, i), v = i < 0 ? '' : decodeURIComponent(kv.slice(i + 1));
      if (k === 'beta') nums(v).forEach(function (x, j) { if (j < MAXC) st.beta[j] = x; });
      else if (k === 'gamma') nums(v).forEach(function (x, j) { if (j < LC) st.gamma[j] = x; });
      else if (k === 'light') st.light = v;
      else if (k === 'rot') st.rot = +v || 0;
      else if (k === 'lp') { var p = nums(v); if (p.length === 3) st.lp = p; }
      else if (k === 'li') { var q = nums(v); if (q.length === 1) q = [q[0], q[0], q[0]]; if (q.length === 3) st.li = q; }
      else if (k === 'cam') { var c = nums(v); for (var j = 0; j < 3 && j < c.length; j++) st.cam[j] = c[j]; }
      else if (k === 'focal') st.focal = +v || null;
      else if (k === 'size') { var m = /^(\d+)x(\d+)$/.exec(v); if (m) st.size = [+m[1], +m[2]]; }
      else if (k === 'layer' && LAYERS.indexOf(v) >= 0) st.layer = v;
      else if (k === 'exposure') st.exposure = +v > 0 ? +v : null;
      else if (k === 'ev') st.ev = +v || 0;
      else if (k === 'display' && DOC.display.transfers.indexOf(v) >= 0) st.display = v;
      else if (k === 'ui') st.ui = v === '0' ? 0 : 1;
      else if (k === 'aa') st.aa = v === '0' ? 0 : 1;
      else if (k === 'split') st.split = v === '0' || models.length < 2 ? 0 : 1;
      else if (k === 'model') st.model = Math.max(0, Math.min(models.length - 1, +v || 0));
    });
    if (!/^(env:\d+|model|point)$/.test(st.light) ||
        (st.light.indexOf('env:') === 0 && +st.light.slice(4) >= envs.length) || (st.light === 'model' && !lmodel))
      st.light = defaultLight();
    return st;
  }
  function fmt(x) { return (+x.toFixed(4)).toString(); }
  function hashOf(st) {
    var parts = ['beta=' + st.beta.map(fmt).join(','), 'light=' + st.light];
    if (st.light === 'model') parts.push('gamma=' + st.gamma.map(fmt).join(','));
    if (st.light !== 'point') parts.push('rot=' + fmt(st.rot));
    else { parts.push('lp=' + st.lp.map(fmt).join(',')); if (st.li) parts.push('li=' + st.li.map(fmt).join(',')); }
    parts.push('cam=' + st.cam.map(fmt).join(','), 'layer=' + st.layer, 'display=' + st.display);
    if (st.exposure) parts.push('exposure=' + st.exposure); else if (st.ev) parts.push('ev=' + fmt(st.ev));
    if (st.focal) parts.push('focal=' + fmt(st.focal));
    if (st.size) parts.push('size=' + st.size[0] + 'x' + st.size[1]);
    if (models.length > 1) parts.push('split=' + st.split, 'model=' + st.model);
    if (!st.ui) parts.push('ui=0');
    if (!st.aa) parts.push('aa=0');
    return '#' + parts.join('&');
  }
  var writingHash = false;
  function saveHash() {
    var h = hashOf(S);
    if (h !== location.hash) { writingHash = true; history.replaceState(null, '', h); writingHash = false; }
  }

  // ------------------------------------------------------------------------------------------------ GL
  S = parseHash(location.hash);
  var canvas = $('view');
  var gl = canvas.getContext('webgl2', { antialias: !!S.aa, preserveDrawingBuffer: true, premultipliedAlpha: false });
  if (!gl) { document.body.setAttribute('data-error', 'no WebGL2'); $('status').textContent = 'This page needs WebGL2.'; return; }

  // The SH basis of shading/sh.py: real, orthonormal, Condon-Shortley phase, index l^2+l+m, the same recurrence
  // and the same constants (embedded), unrolled for the bundle's order.
  function lit(x) { var s = (+x).toPrecision(12); return /[.eE]/.test(s) ? s : s + '.0'; }
  function shSource() {
    var R = SH.recurrence, src = ['void shEval(vec3 d, out float Y[NSH]) {',
      '  float x = d.x, y = d.y, z = d.z, cm = 1.0, sm = 0.0, t, q, q1, q2;'];
    for (var m = 0; m <= ORDER; m++) {
      if (m === 1) src.push('  cm = x; sm = y;');
      else if (m > 1) src.push('  t = x * cm - y * sm; sm = x * sm + y * cm; cm = t;');
      for (var l = m; l <= ORDER; l++) {
        if (l === m) src.push('  q1 = ' + lit(R.pmm[m]) + '; q = q1;');
        else if (l === m + 1) src.push('  q = ' + lit(Math.sqrt(2 * m + 3) * R.pmm[m]) + ' * z; q2 = q1; q1 = q;');
        else src.push('  q = ' + lit(R.a[m][l]) + ' * (z * q1 - ' + lit(R.b[m][l]) + ' * q2); q2 = q1; q1 = q;');
        if (m === 0) src.push('  Y[' + (l * l + l) + '] = q;');
        else src.push('  Y[' + (l * l + l + m) + '] = ' + lit(Math.SQRT2) + ' * q * cm; Y[' + (l * l + l - m) +
          '] = ' + lit(Math.SQRT2) + ' * q * sm;');
      }
    }
    src.push('}');
    return src.join('\n');
  }

  var VS = ['#version 300 es', 'precision highp float;',
    'in vec3 aPos; in vec3 aNrm; in vec3 aAlb; in vec4 aW0; in vec4 aW1;',
    'uniform mat4 uView; uniform mat4 uProj;',
    'out vec3 vPos; out vec3 vNrm; out vec3 vAlb; out vec4 vW0; out vec4 vW1;',
    'void main() { vPos = aPos; vNrm = aNrm; vAlb = aAlb; vW0 = aW0; vW1 = aW1;',
    '  gl_Position = uProj * uView * vec4(aPos, 1.0); }'].join('\n');

  function fsSource() {
    return ['#version 300 es', 'precision highp float; precision highp int; precision highp sampler2D;',
      '#define NSH ' + NSH,
      'in vec3 vPos; in vec3 vNrm; in vec3 vAlb; in vec4 vW0; in vec4 vW1; out vec4 outColor;',
      'uniform sampler2D uCoef;   // row 0: (A_l/pi) K_lm, row 1+i: B_l^i K_lm (rgb)',
      'uniform vec4 uP0, uP1;     // lobe exponents',
      'uniform vec4 uF0, uF1;     // lobe normalisations f_i',
      'uniform vec4 uM0, uM1;     // lobe selection (1 = shaded / shown)',
      'uniform int uNLobes, uLayer, uPoint, uTransfer;',
      'uniform vec3 uEye, uLightPos, uLightI; uniform float uExposure; uniform mat3 uEnvRot;',
      shSource(),
      'vec3 encode(vec3 x) {',
      '  x = clamp(x, 0.0, 1.0);',
      '  if (uTransfer == 1) return pow(x, vec3(1.0 / 1.2));',
      '  return mix(12.92 * x, 1.055 * pow(x, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), x));',
      '}',
      'void main() {',
      '  vec3 n = normalize(vNrm), v = normalize(uEye - vPos), c = vAlb;',
      '  vec4 w0 = vW0 * uM0, w1 = vW1 * uM1;',
      '  if (uLayer == 3) { outColor = vec4(encode(c), 1.0); return; }',
      '  if (uLayer == 4) { float s = dot(vW0, vec4(1.0)) + dot(vW1, vec4(1.0)); outColor = vec4(encode(vec3(s)), 1.0); return; }',
      '  if (uLayer == 5) { float s = dot(w0, vec4(1.0)) + dot(w1, vec4(1.0)); outColor = vec4(encode(vec3(s)), 1.0); return; }',
      '  vec3 dif = vec3(0.0), spe = vec3(0.0);',
      '  float ndv = dot(n, v);',
      '  if (uPoint == 1) {',
      '    vec3 ld = uLightPos - vPos; float d2 = max(dot(ld, ld), 1e-30); vec3 l = normalize(ld);',
      '    float ndl = dot(n, l);',
      '    if (ndl > 0.0 && ndv > 0.0) {',
      '      vec3 E = uLightI / d2; vec3 hv = l + v; float hl = length(hv);',
      '      float ndh = hl > 0.0 ? dot(n, hv / hl) : 0.0; ndh = max(ndh, 0.0);',
      '      float s = 0.0;',
      '      for (int i = 0; i < 4; i++) if (i < uNLobes) s += w0[i] * uF0[i] * pow(ndh, uP0[i]);',
      '      for (int i = 0; i < 4; i++) if (i + 4 < uNLobes) s += w1[i] * uF1[i] * pow(ndh, uP1[i]);',
      '      dif = E * c * (ndl / 3.141592653589793); spe = E * s;',
      '    }',
      '  } else {',
      '    float Y[NSH];',
      '    shEval(uEnvRot * n, Y);',
      '    vec3 irr = vec3(0.0);',
      '    for (int j = 0; j < NSH; j++) irr += Y[j] * texelFetch(uCoef, ivec2(j, 0), 0).rgb;',
      '    dif = c * irr;',
      '    if (ndv > 0.0) {',
      '      shEval(uEnvRot * (2.0 * ndv * n - v), Y);',
      '      for (int i = 0; i < 8; i++) {',
      '        if (i >= uNLobes) break;',
      '        float wi = i < 4 ? w0[i] : w1[i - 4];',
      '        if (wi == 0.0) continue;',
      '        vec3 acc = vec3(0.0);',
      '        for (int j = 0; j < NSH; j++) acc += Y[j] * texelFetch(uCoef, ivec2(j, 1 + i), 0).rgb;',
      '        spe += wi * acc;',
      '      }',
      '    }',
      '  }',
      '  vec3 rad = uLayer == 1 ? dif : (uLayer == 2 ? spe : dif + spe);',
      '  outColor = vec4(encode(rad * uExposure), 1.0);',
      '}'].join('\n');
  }

  function compile(type, src) {
    var s = gl.createShader(type);
    gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  var prog = gl.createProgram();
  gl.attachShader(prog, compile(gl.VERTEX_SHADER, VS));
  gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, fsSource()));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  gl.useProgram(prog);
  var U = {};
  ['uView', 'uProj', 'uCoef', 'uP0', 'uP1', 'uF0', 'uF1', 'uM0', 'uM1', 'uNLobes', 'uLayer', 'uPoint', 'uTransfer',
    'uEye', 'uLightPos', 'uLightI', 'uExposure', 'uEnvRot'].forEach(function (k) { U[k] = gl.getUniformLocation(prog, k); });

  function buffer(data, target) {
    var b = gl.createBuffer(); gl.bindBuffer(target || gl.ARRAY_BUFFER, b);
    gl.bufferData(target || gl.ARRAY_BUFFER, data, gl.STATIC_DRAW); return b;
  }
  function attrib(name, buf, size) {
    var loc = gl.getAttribLocation(prog, name);
    if (loc < 0) return;
    gl.bindBuffer(gl.ARRAY_BUFFER, buf); gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, size, gl.FLOAT, false, 0, 0);
  }
  var geo = { pos: buffer(mesh.pos), nrm: buffer(mesh.nrm), idx: buffer(mesh.tri, gl.ELEMENT_ARRAY_BUFFER) };
  var idxType = mesh.tri instanceof Uint32Array ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT;
  // per model: one VAO with its own reflectance buffers (albedo vec3, weights 2 x vec4)
  models.forEach(function (m) {
    m.vao = gl.createVertexArray(); gl.bindVertexArray(m.vao);
    attrib('aPos', geo.pos, 3); attrib('aNrm', geo.nrm, 3);
    m.alb = new Float32Array(mesh.n * 3); m.w0 = new Float32Array(mesh.n * 4); m.w1 = new Float32Array(mesh.n * 4);
    m.balb = buffer(m.alb); m.bw0 = buffer(m.w0); m.bw1 = buffer(m.w1);
    attrib('aAlb', m.balb, 3); attrib('aW0', m.bw0, 4); attrib('aW1', m.bw1, 4);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, geo.idx);
    gl.bindVertexArray(null);
  });
  var coefTex = gl.createTexture();

  // Reflectance of a model at beta: mu + sum_k beta_k sigma_k basis_k, per vertex (model/pca.py sample_model).
  function updateReflectance(m) {
    var N = mesh.n, K = m.K, alb = m.alb, w0 = m.w0, w1 = m.w1;
    alb.set(m.am); w0.fill(0); w1.fill(0);
    var w = new Float32Array(N * K); w.set(m.wm);
    for (var k = 0; k < m.M; k++) {
      var s = S.beta[k] * m.sigma[k];
      if (!s) continue;
      var oa = k * N * 3, ow = k * N * K, i;
      for (i = 0; i < N * 3; i++) alb[i] += s * m.ab[oa + i];
      for (i = 0; i < N * K; i++) w[i] += s * m.wb[ow + i];
    }
    for (var v = 0; v < N; v++) for (var j = 0; j < K; j++) {
      if (j < 4) w0[v * 4 + j] = w[v * K + j]; else w1[v * 4 + j - 4] = w[v * K + j];
    }
    gl.bindBuffer(gl.ARRAY_BUFFER, m.balb); gl.bufferSubData(gl.ARRAY_BUFFER, 0, alb);
    gl.bindBuffer(gl.ARRAY_BUFFER, m.bw0); gl.bufferSubData(gl.ARRAY_BUFFER, 0, w0);
    gl.bindBuffer(gl.ARRAY_BUFFER, m.bw1); gl.bufferSubData(gl.ARRAY_BUFFER, 0, w1);
  }

  // SH radiance coefficients (3 x NSH, channel-major) of the current environment light.
  function envCoeffs() {
    var K = new Float32Array(3 * NSH);
    if (S.light.indexOf('env:') === 0) { K.set(envs[+S.light.slice(4)].sh); return K; }
    var n = (lmodel.order + 1) * (lmodel.order + 1), F = 3 * n;
    for (var c = 0; c < 3; c++) for (var i = 0; i < n; i++) {
      var x = lmodel.mean[c * n + i];
      for (var k = 0; k < LC; k++) x += S.gamma[k] * lmodel.sigma[k] * lmodel.bases[k * F + c * n + i];
      K[c * NSH + i] = lmodel.level[c] * x;
    }
    return K;
  }
  // The coefficient texture of model m: row 0 (A_l/pi) K_lm, row 1+i B_l^i K_lm.
  function uploadCoeffs(mi) {
    var K = envCoeffs(), lobes = SH.lobes[mi], nk = models[mi].K, rows = 1 + nk, data = new Float32Array(NSH * rows * 4);
    for (var l = 0; l <= ORDER; l++) for (var mm = -l; mm <= l; mm++) {
      var j = l * l + l + mm;
      for (var r = 0; r < rows; r++) {
        var f = r === 0 ? SH.lambert_over_pi[l] : lobes.B[r - 1][l];
        for (var c = 0; c < 3; c++) data[(r * NSH + j) * 4 + c] = f * K[c * NSH + j];
        data[(r * NSH + j) * 4 + 3] = 1;
      }
    }
    gl.bindTexture(gl.TEXTURE_2D, coefTex);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, NSH, rows, 0, gl.RGBA, gl.FLOAT, data);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  }

  // Orbit camera of geometry/camera.py orbit_camera: eye on a sphere around the origin, +y up; the projection
  // of a pinhole with focal f (pixels) and the principal point at the image centre.
  function eyeOf(st) {
    var y = st.cam[0] * Math.PI / 180, p = st.cam[1] * Math.PI / 180, d = st.cam[2];
    return [d * Math.sin(y) * Math.cos(p), d * Math.sin(p), d * Math.cos(y) * Math.cos(p)];
  }
  function viewMatrix(eye) {
    var z = norm3(eye), up = [0, 1, 0], x = norm3(cross(up, z)), y = cross(z, x);
    return [x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0,
      -dot(x, eye), -dot(y, eye), -dot(z, eye), 1];
  }
  function projMatrix(f, w, h, near, far) {
    return [2 * f / w, 0, 0, 0, 0, 2 * f / h, 0, 0, 0, 0, (far + near) / (near - far), -1,
      0, 0, 2 * far * near / (near - far), 0];
  }
  function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function norm3(a) { var l = Math.sqrt(dot(a, a)) || 1; return [a[0] / l, a[1] / l, a[2] / l]; }
  function focalPx(h) { return S.focal || DOC.camera.focal * h / DOC.camera.focal_height; }

  function exposure() {
    if (S.exposure) return S.exposure;
    var base = S.light === 'point' ? DOC.lights.point_exposure :
      (S.light === 'model' ? lmodel.exposure : envs[+S.light.slice(4)].exposure);
    if (S.light === 'point' && S.li) {  // the default exposure is for irradiance pi at the origin
      var d2 = dot(S.lp, S.lp), e = (S.li[0] + S.li[1] + S.li[2]) / 3;
      if (e > 0) base *= Math.PI * d2 / e;
    }
    return base * Math.pow(2, S.ev);
  }
  function layerCode() {
    var L = S.layer;
    if (L === 'full') return [0, -1]; if (L === 'diffuse') return [1, -1]; if (L === 'specular') return [2, -1];
    if (L === 'albedo') return [3, -1]; if (L === 'sumw') return [4, -1];
    if (L.indexOf('lobe') === 0) return [2, +L.slice(4)];
    return [5, +L.slice(6)];
  }

  var dirty = { refl: true };
  function resize() {
    var w, h;
    if (S.size) { w = S.size[0]; h = S.size[1]; } else {
      var r = canvas.parentNode.getBoundingClientRect(); w = Math.max(1, Math.round(r.width)); h = Math.max(1, Math.round(r.height));
    }
    canvas.style.width = w + 'px'; canvas.style.height = h + 'px';
    var dpr = S.size ? 1 : (window.devicePixelRatio || 1);
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
    }
  }
  function draw() {
    resize();
    if (dirty.refl) { models.forEach(updateReflectance); dirty.refl = false; }
    var W = canvas.width, H = canvas.height, views = S.split && models.length > 1 ? [0, 1] : [S.model];
    var eye = eyeOf(S), view = viewMatrix(eye), lc = layerCode(), th = -S.rot * Math.PI / 180;
    var ct = Math.cos(th), st = Math.sin(th);
    gl.enable(gl.DEPTH_TEST);  // no culling: the renderer's rays see back faces too
    gl.clearColor(0, 0, 0, 1); gl.viewport(0, 0, W, H); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    var li = S.li || [Math.PI * dot(S.lp, S.lp), Math.PI * dot(S.lp, S.lp), Math.PI * dot(S.lp, S.lp)];
    views.forEach(function (mi, vi) {
      var m = models[mi], vw = Math.floor(W / views.length), x0 = vi * vw;
      gl.viewport(x0, 0, vw, H);
      var near = Math.max(1, S.cam[2] * 0.05), far = S.cam[2] * 4 + 1000;
      gl.uniformMatrix4fv(U.uView, false, view);
      gl.uniformMatrix4fv(U.uProj, false, projMatrix(focalPx(H), vw, H, near, far));
      var P = m.exponents.concat([1, 1, 1, 1, 1, 1, 1, 1]).slice(0, 8), F = SH.lobes[mi].norm.concat([0, 0, 0, 0, 0, 0, 0, 0]).slice(0, 8);
      var sel = []; for (var i = 0; i < 8; i++) sel.push(lc[1] < 0 || lc[1] === i ? 1 : 0);
      gl.uniform4fv(U.uP0, P.slice(0, 4)); gl.uniform4fv(U.uP1, P.slice(4, 8));
      gl.uniform4fv(U.uF0, F.slice(0, 4)); gl.uniform4fv(U.uF1, F.slice(4, 8));
      gl.uniform4fv(U.uM0, sel.slice(0, 4)); gl.uniform4fv(U.uM1, sel.slice(4, 8));
      gl.uniform1i(U.uNLobes, m.K); gl.uniform1i(U.uLayer, lc[0]); gl.uniform1i(U.uPoint, S.light === 'point' ? 1 : 0);
      gl.uniform1i(U.uTransfer, S.display === 'gamma1.2' ? 1 : 0);
      gl.uniform3fv(U.uEye, eye); gl.uniform3fv(U.uLightPos, S.lp); gl.uniform3fv(U.uLightI, li);
      gl.uniform1f(U.uExposure, exposure());
      // the environment turned by rot about +y: look up the map at R_y(-rot) d (column-major mat3)
      gl.uniformMatrix3fv(U.uEnvRot, false, [ct, 0, -st, 0, 1, 0, st, 0, ct]);
      if (S.light !== 'point') { uploadCoeffs(mi); gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, coefTex); gl.uniform1i(U.uCoef, 0); }
      gl.bindVertexArray(m.vao);
      gl.drawElements(gl.TRIANGLES, mesh.tri.length, idxType, 0);
      gl.bindVertexArray(null);
    });
    labels(views);
    saveHash();
    document.body.setAttribute('data-hash', hashOf(S));
    document.body.setAttribute('data-frames', String(+(document.body.getAttribute('data-frames') || 0) + 1));
  }
  var pending = false;
  function redraw() { if (!pending) { pending = true; requestAnimationFrame(function () { pending = false; draw(); }); } }

  // ------------------------------------------------------------------------------------------------ UI
  function labels(views) {
    var box = $('labels'); box.innerHTML = '';
    if (views.length < 2 && models.length < 2) return;
    views.forEach(function (mi) {
      var d = document.createElement('div'); d.className = 'label'; d.textContent = models[mi].name; box.appendChild(d);
    });
  }
  function el(tag, attrs, text) {
    var e = document.createElement(tag);
    for (var k in attrs) if (Object.prototype.hasOwnProperty.call(attrs, k)) e.setAttribute(k, attrs[k]);
    if (text != null) e.textContent = text;
    return e;
  }
  function slider(parent, label, min, max, step, get, set) {
    var row = el('div', { 'class': 'row' }), lab = el('label', {}, label), inp = el('input', { type: 'range', min: min, max: max, step: step });
    var out = el('span', { 'class': 'val' });
    inp.value = get(); out.textContent = (+get()).toFixed(2);
    inp.addEventListener('input', function () { set(+inp.value); out.textContent = (+inp.value).toFixed(2); redraw(); });
    row.appendChild(lab); row.appendChild(inp); row.appendChild(out); parent.appendChild(row);
    return { sync: function () { inp.value = get(); out.textContent = (+get()).toFixed(2); } };
  }
  function select(parent, label, options, get, set) {
    var row = el('div', { 'class': 'row' }), lab = el('label', {}, label), s = el('select', {});
    options.forEach(function (o) { s.appendChild(el('option', { value: o[0] }, o[1])); });
    s.value = get();
    s.addEventListener('change', function () { set(s.value); redraw(); syncAll(); });
    row.appendChild(lab); row.appendChild(s); parent.appendChild(row);
    return { sync: function () { s.value = get(); } };
  }
  var syncers = [];
  function syncAll() {
    syncers.forEach(function (s) { s.sync(); });
    $('gammas').style.display = S.light === 'model' ? '' : 'none';
    $('rotrow').style.display = S.light === 'point' ? 'none' : '';
    $('pointrow').style.display = S.light === 'point' ? '' : 'none';
  }
  function buildPanel() {
    var p = $('panel');
    p.appendChild(el('h1', {}, DOC.title || 'reflectmm model'));
    var info = models.map(function (m) {
      return m.name + ': ' + m.K + ' lobe' + (m.K > 1 ? 's' : '') + ' (p = ' + m.exponents.join(', ') + '), ' + m.M + ' components';
    }).join('; ');
    p.appendChild(el('p', { 'class': 'info' }, info + '. ' + mesh.n + ' vertices.'));
    var sec = el('details', { open: '' }); sec.appendChild(el('summary', {}, 'Reflectance coefficients β (σ)')); p.appendChild(sec);
    var b = el('div', { 'class': 'row' });
    var rnd = el('button', { id: 'random' }, 'random sample'), zero = el('button', { id: 'mean' }, 'mean');
    rnd.addEventListener('click', function () {
      for (var k = 0; k < MAXC; k++) {  // standard normal (Box-Muller), clipped at ±3σ
        var u = 1 - Math.random(), v = Math.random();
        S.beta[k] = Math.max(-3, Math.min(3, Math.sqrt(-2 * Math.log(u)) * Math.cos(2 * Math.PI * v)));
      }
      dirty.refl = true; syncAll(); redraw();
    });
    zero.addEventListener('click', function () { S.beta.fill(0); dirty.refl = true; syncAll(); redraw(); });
    b.appendChild(rnd); b.appendChild(zero); sec.appendChild(b);
    for (var k = 0; k < MAXC; k++) (function (k) {
      syncers.push(slider(sec, 'β' + (k + 1), -3, 3, 0.01, function () { return S.beta[k]; },
        function (x) { S.beta[k] = x; dirty.refl = true; }));
    })(k);
    var ls = el('details', { open: '' }); ls.appendChild(el('summary', {}, 'Light')); p.appendChild(ls);
    var opts = envs.map(function (e, i) { return ['env:' + i, 'environment: ' + e.name]; });
    if (lmodel) opts.push(['model', 'light model (γ)']);
    opts.push(['point', 'point light (drag with shift, or in light mode)']);
    syncers.push(select(ls, 'light', opts, function () { return S.light; }, function (v) { S.light = v; }));
    var rr = el('div', { id: 'rotrow' }); ls.appendChild(rr);
    syncers.push(slider(rr, 'rotation°', 0, 360, 1, function () { return S.rot; }, function (x) { S.rot = x; }));
    var gs = el('div', { id: 'gammas' }); ls.appendChild(gs);
    for (var g = 0; g < LC; g++) (function (g) {
      syncers.push(slider(gs, 'γ' + (g + 1), -3, 3, 0.01, function () { return S.gamma[g]; }, function (x) { S.gamma[g] = x; }));
    })(g);
    var pr = el('div', { id: 'pointrow' }); ls.appendChild(pr);
    var mode = el('button', { id: 'lightmode' }, 'drag: orbit');
    mode.addEventListener('click', function () { dragLight = !dragLight; mode.textContent = dragLight ? 'drag: light' : 'drag: orbit'; });
    pr.appendChild(mode);
    var vs = el('details', { open: '' }); vs.appendChild(el('summary', {}, 'View')); p.appendChild(vs);
    var lay = [['full', 'full'], ['diffuse', 'diffuse'], ['specular', 'specular']];
    for (var i = 0; i < MAXK; i++) lay.push(['lobe' + i, 'lobe ' + (i + 1) + ' alone (p = ' + models[0].exponents[Math.min(i, models[0].K - 1)] + ')']);
    lay.push(['albedo', 'diffuse albedo'], ['sumw', 'Σw (specular albedo)']);
    for (i = 0; i < MAXK; i++) lay.push(['weight' + i, 'weight of lobe ' + (i + 1)]);
    syncers.push(select(vs, 'layer', lay, function () { return S.layer; }, function (v) { S.layer = v; }));
    syncers.push(slider(vs, 'exposure (EV)', -6, 6, 0.1, function () { return S.ev; }, function (x) { S.ev = x; S.exposure = null; }));
    syncers.push(select(vs, 'display', [['srgb', 'sRGB'], ['gamma1.2', 'x^(1/1.2)']], function () { return S.display; },
      function (v) { S.display = v; }));
    if (models.length > 1) {
      syncers.push(select(vs, 'models', [['1', 'side by side']].concat(models.map(function (m, i) { return ['m' + i, m.name]; })),
        function () { return S.split ? '1' : 'm' + S.model; },
        function (v) { if (v === '1') S.split = 1; else { S.split = 0; S.model = +v.slice(1); } }));
    }
    var r = el('div', { 'class': 'row' }), reset = el('button', { id: 'reset' }, 'reset view'), save = el('button', { id: 'save' }, 'save PNG');
    reset.addEventListener('click', function () { var d = defaultState(); S.cam = d.cam; S.focal = null; redraw(); });
    save.addEventListener('click', function () {
      var a = document.createElement('a'); a.download = 'reflectmm-view.png'; a.href = canvas.toDataURL('image/png'); a.click();
    });
    r.appendChild(reset); r.appendChild(save); vs.appendChild(r);
    p.appendChild(el('p', { 'class': 'help' }, 'Drag: orbit. Wheel: zoom. Shift-drag (or light mode): move the point light. ' +
      'The view is in the address (#…): copy it to share this view.'));
    syncAll();
  }

  // pointer: orbit, zoom, light
  var dragLight = false, drag = null;
  canvas.addEventListener('pointerdown', function (e) {
    drag = { x: e.clientX, y: e.clientY, cam: S.cam.slice(), light: dragLight || e.shiftKey };
    canvas.setPointerCapture(e.pointerId);
    if (drag.light) moveLight(e);
  });
  canvas.addEventListener('pointermove', function (e) {
    if (!drag) return;
    if (drag.light) { moveLight(e); return; }
    S.cam[0] = drag.cam[0] - (e.clientX - drag.x) * 0.4;
    S.cam[1] = Math.max(-89, Math.min(89, drag.cam[1] + (e.clientY - drag.y) * 0.4));
    redraw();
  });
  canvas.addEventListener('pointerup', function () { drag = null; });
  canvas.addEventListener('wheel', function (e) {
    e.preventDefault(); S.cam[2] = Math.max(100, Math.min(20000, S.cam[2] * Math.exp(e.deltaY * 0.001))); redraw();
  }, { passive: false });
  // The light on the hemisphere facing the camera, under the pointer, at the camera's distance.
  function moveLight(e) {
    var r = canvas.getBoundingClientRect(), n = S.split && models.length > 1 ? 2 : 1, w = r.width / n;
    var px = ((e.clientX - r.left) % w) / w * 2 - 1, py = 1 - (e.clientY - r.top) / r.height * 2;
    var len = Math.sqrt(px * px + py * py); if (len > 0.999) { px *= 0.999 / len; py *= 0.999 / len; }
    var pz = Math.sqrt(Math.max(0, 1 - px * px - py * py));
    var eye = eyeOf(S), z = norm3(eye), x = norm3(cross([0, 1, 0], z)), y = cross(z, x), d = S.cam[2];
    S.lp = [0, 1, 2].map(function (i) { return d * (px * x[i] + py * y[i] + pz * z[i]); });
    if (S.light !== 'point') { S.light = 'point'; syncAll(); }
    redraw();
  }
  window.addEventListener('resize', redraw);
  window.addEventListener('hashchange', function () {
    if (writingHash) return;
    S = parseHash(location.hash); dirty.refl = true; applyUi(); syncAll(); redraw();
  });
  function applyUi() { document.body.classList.toggle('noui', !S.ui); }

  buildPanel();
  applyUi();
  // ?frames=N (a query, not state): time N redraws to the end of the GPU work; the result goes to data-ms-per-frame
  function timeFrames(n) {
    var t0 = performance.now();
    for (var i = 0; i < n; i++) { dirty.refl = true; draw(); gl.finish(); }
    var px = new Uint8Array(4); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    document.body.setAttribute('data-ms-per-frame', ((performance.now() - t0) / n).toFixed(2));
  }
  try {
    draw(); document.body.setAttribute('data-ready', '1');
    var fq = /[?&]frames=(\d+)/.exec(location.search);
    if (fq) timeFrames(+fq[1]);
  } catch (err) {
    document.body.setAttribute('data-error', String(err)); $('status').textContent = String(err); throw err;
  }
})();
