// flamenerf's web player: a baked avatar (window.FLAMENERF_AVATAR, written by
// `flamenerf export --web`) drawn with WebGL2 as flamenerf's reference rasteriser draws it
// (splats/rasterise.py): each splat a point sprite of side size*fx/depth pixels, clamped
// to [1, 32], its depth receding towards its edges, nearest wins; the face's splats moved
// and recoloured by the expression's offsets in the vertex shader.
"use strict";

(function () {
  const A = window.FLAMENERF_AVATAR;
  const MAX_POINT_PX = 32.0;
  const BULGE = A.bulge;
  const TEX_W = 2048;

  function bytes(b64) {
    const s = atob(b64);
    const out = new Uint8Array(s.length);
    for (let i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
    return out;
  }
  const positions = new Float32Array(bytes(A.positions).buffer);
  const colours = bytes(A.colours);
  const sizes = new Float32Array(bytes(A.sizes).buffer);
  const faceIndex = new Int32Array(bytes(A.faceIndex).buffer);
  const dPos = new Uint16Array(bytes(A.dPositions).buffer); // half floats, (K, F, 3)
  const dCol = new Uint16Array(bytes(A.dColours).buffer);
  const N = A.n, F = A.f, K = A.names.length;

  const params = new URLSearchParams(location.search);
  const bare = params.has("bare");
  const intr0 = A.meta.intrinsics;
  const W = parseInt(params.get("w") || (bare ? intr0.w : 512), 10);
  const H = parseInt(params.get("h") || Math.round(W * intr0.h / intr0.w), 10);
  const scale = W / intr0.w;
  const intr = { fx: intr0.fx * scale, fy: intr0.fy * (H / intr0.h), cx: intr0.cx * scale,
                 cy: intr0.cy * (H / intr0.h) };

  const canvas = document.getElementById("view");
  canvas.width = W; canvas.height = H;
  canvas.style.width = W + "px"; canvas.style.height = H + "px";
  const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true,
                                           alpha: false });
  if (!gl) {
    document.getElementById("status").textContent = "This browser has no WebGL2.";
    return;
  }

  const vs = `#version 300 es
  precision highp float; precision highp int;
  in vec3 a_pos; in vec3 a_col; in float a_size; in float a_face;
  uniform mat4 u_view; uniform mat4 u_proj; uniform float u_fx;
  uniform highp sampler2D u_dpos; uniform highp sampler2D u_dcol;
  uniform float u_delta[64]; uniform int u_k; uniform int u_f;
  out vec3 v_col; out float v_depth; out float v_size;
  void main() {
    vec3 p = a_pos; vec3 c = a_col;
    int j = int(a_face);
    if (j >= 0) {
      for (int k = 0; k < 64; k++) {
        if (k >= u_k) break;
        float b = u_delta[k];
        if (b == 0.0) continue;
        int t = k * u_f + j;
        ivec2 xy = ivec2(t % ${TEX_W}, t / ${TEX_W});
        p += b * texelFetch(u_dpos, xy, 0).xyz;
        c += b * texelFetch(u_dcol, xy, 0).xyz;
      }
    }
    vec4 cam = u_view * vec4(p, 1.0);
    float depth = -cam.z;
    gl_Position = u_proj * cam;
    gl_PointSize = clamp(a_size * u_fx / max(depth, 1e-3), 1.0, ${MAX_POINT_PX.toFixed(1)});
    v_col = clamp(c, 0.0, 1.0); v_depth = depth; v_size = a_size;
  }`;
  const fs = `#version 300 es
  precision highp float;
  in vec3 v_col; in float v_depth; in float v_size;
  uniform float u_near; uniform float u_far;
  out vec4 colour;
  void main() {
    vec2 r = (gl_PointCoord - 0.5) * 2.0;
    float d = v_depth + ${BULGE.toFixed(4)} * v_size * dot(r, r);
    float ndc = (u_far + u_near) / (u_far - u_near) - 2.0 * u_far * u_near / ((u_far - u_near) * d);
    gl_FragDepth = clamp(0.5 * ndc + 0.5, 0.0, 1.0);
    colour = vec4(v_col, 1.0);
  }`;

  function shader(type, src) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  const prog = gl.createProgram();
  gl.attachShader(prog, shader(gl.VERTEX_SHADER, vs));
  gl.attachShader(prog, shader(gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  gl.useProgram(prog);

  function attribute(name, data, comps, type, normalised) {
    const loc = gl.getAttribLocation(prog, name);
    const buf = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, buf);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, comps, type, normalised, 0, 0);
  }
  const face = new Float32Array(N).fill(-1);
  for (let j = 0; j < F; j++) face[faceIndex[j]] = j;
  const vao = gl.createVertexArray();
  gl.bindVertexArray(vao);
  attribute("a_pos", positions, 3, gl.FLOAT, false);
  attribute("a_col", colours, 3, gl.UNSIGNED_BYTE, true);
  attribute("a_size", sizes, 1, gl.FLOAT, false);
  attribute("a_face", face, 1, gl.FLOAT, false);

  function offsets(unit, half3) { // (K*F, 3) half floats -> an RGBA16F texture
    const n = Math.max(K * F, 1), rows = Math.ceil(n / TEX_W);
    const data = new Uint16Array(TEX_W * rows * 4);
    for (let t = 0; t < K * F; t++) {
      data[4 * t] = half3[3 * t]; data[4 * t + 1] = half3[3 * t + 1];
      data[4 * t + 2] = half3[3 * t + 2];
    }
    const tex = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA16F, TEX_W, rows, 0, gl.RGBA, gl.HALF_FLOAT, data);
  }
  offsets(0, dPos); offsets(1, dCol);
  const U = (n) => gl.getUniformLocation(prog, n);
  gl.uniform1i(U("u_dpos"), 0); gl.uniform1i(U("u_dcol"), 1);
  gl.uniform1i(U("u_k"), K); gl.uniform1i(U("u_f"), F);
  gl.uniform1f(U("u_fx"), intr.fx);
  const near = A.meta.near, far = A.meta.far * 4.0;
  gl.uniform1f(U("u_near"), near); gl.uniform1f(U("u_far"), far);
  // pixel-exact pinhole projection (OpenGL axes: x right, y up, looking down -z)
  const proj = new Float32Array([
    2 * intr.fx / W, 0, 0, 0,
    0, 2 * intr.fy / H, 0, 0,
    1 - 2 * intr.cx / W, 2 * intr.cy / H - 1, -(far + near) / (far - near), -1,
    0, 0, -2 * far * near / (far - near), 0]);
  gl.uniformMatrix4fv(U("u_proj"), false, proj);
  gl.enable(gl.DEPTH_TEST); gl.depthFunc(gl.LESS);
  gl.viewport(0, 0, W, H);

  function inverseRigid(c2w) { // row-major 4x4 camera-to-world -> column-major world-to-camera
    const m = new Float32Array(16);
    for (let r = 0; r < 3; r++) {
      for (let c = 0; c < 3; c++) m[c * 4 + r] = c2w[c * 4 + r]; // R^T
      let t = 0;
      for (let c = 0; c < 3; c++) t -= c2w[c * 4 + r] * c2w[c * 4 + 3];
      m[12 + r] = t;
    }
    m[15] = 1;
    return m;
  }
  const beta = Float32Array.from(A.reference);
  function draw(c2w) {
    gl.uniformMatrix4fv(U("u_view"), false, inverseRigid(c2w));
    const delta = new Float32Array(64);
    for (let k = 0; k < K; k++) delta[k] = beta[k] - A.reference[k];
    gl.uniform1fv(U("u_delta"), delta);
    gl.clearColor(0, 0, 0, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.drawArrays(gl.POINTS, 0, N);
  }

  // the orbit: about the head's centre, around the scene's up and the camera's right
  const c0 = A.meta.camera.flat();
  const centre = A.meta.center, up = A.meta.up;
  const orbit = { yaw: 0, pitch: 0, zoom: 1 };
  function rotate(v, axis, ang) { // Rodrigues
    const [x, y, z] = axis, c = Math.cos(ang), s = Math.sin(ang);
    const d = x * v[0] + y * v[1] + z * v[2];
    const cr = [y * v[2] - z * v[1], z * v[0] - x * v[2], x * v[1] - y * v[0]];
    return [0, 1, 2].map((i) => v[i] * c + cr[i] * s + axis[i] * d * (1 - c));
  }
  function orbitCamera() {
    const col = (j) => [c0[j], c0[4 + j], c0[8 + j]];
    let cols = [col(0), col(1), col(2)];
    let eye = [c0[3] - centre[0], c0[7] - centre[1], c0[11] - centre[2]];
    const right = cols[0];
    const turn = (v) => rotate(rotate(v, right, orbit.pitch), up, orbit.yaw);
    cols = cols.map(turn);
    eye = turn(eye).map((e, i) => centre[i] + e * orbit.zoom);
    const m = [];
    for (let r = 0; r < 3; r++) m.push(cols[0][r], cols[1][r], cols[2][r], eye[r]);
    m.push(0, 0, 0, 1);
    return m;
  }
  let pending = false;
  function redraw() {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => { pending = false; draw(orbitCamera()); });
  }

  window.flamenerf = { draw, beta, names: A.names, orbit, redraw };

  if (params.has("c2w")) { // a given camera and expression, for a screenshot
    const c2w = params.get("c2w").split(",").map(Number);
    if (params.has("beta")) params.get("beta").split(",").map(Number).forEach((b, k) => beta[k] = b);
    draw(c2w);
    document.title = "drawn";
  }
  if (params.has("bench")) { // frames drawn one after another, each finished
    const n = parseInt(params.get("bench"), 10);
    const px = new Uint8Array(4);
    draw(orbitCamera()); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    const t0 = performance.now();
    for (let i = 0; i < n; i++) {
      for (let k = 0; k < K; k++) {
        beta[k] = A.low[k] + (A.high[k] - A.low[k]) * 0.5 * (1 + Math.sin(i * 0.3 + k));
      }
      orbit.yaw = 0.3 * Math.sin(i * 0.1);
      draw(orbitCamera());
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    }
    const fps = n / ((performance.now() - t0) / 1000);
    document.getElementById("result").textContent = JSON.stringify({ frames: n, fps, w: W, h: H });
    document.title = "fps " + fps.toFixed(1);
  }
  if (bare) return;

  // the controls: one slider per control over its range, orbit by dragging, zoom by wheel
  const panel = document.getElementById("controls");
  const sliders = [];
  A.names.forEach((name, k) => {
    const row = document.createElement("label");
    const s = document.createElement("input");
    s.type = "range"; s.min = A.low[k]; s.max = A.high[k]; s.step = 0.01;
    s.value = A.reference[k];
    s.disabled = !(A.high[k] - A.low[k] > 0.02);
    s.oninput = () => { beta[k] = parseFloat(s.value); redraw(); };
    row.append(s, " " + name);
    panel.append(row);
    sliders.push(s);
  });
  document.getElementById("reset").onclick = () => {
    A.reference.forEach((v, k) => { beta[k] = v; sliders[k].value = v; });
    orbit.yaw = orbit.pitch = 0; orbit.zoom = 1; redraw();
  };
  let drag = null;
  canvas.onpointerdown = (e) => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); };
  canvas.onpointerup = () => { drag = null; };
  canvas.onpointermove = (e) => {
    if (!drag) return;
    orbit.yaw -= (e.clientX - drag[0]) * 0.005;
    orbit.pitch = Math.max(-1.2, Math.min(1.2, orbit.pitch - (e.clientY - drag[1]) * 0.005));
    drag = [e.clientX, e.clientY]; redraw();
  };
  canvas.onwheel = (e) => {
    e.preventDefault();
    orbit.zoom = Math.max(0.3, Math.min(3, orbit.zoom * Math.exp(e.deltaY * 0.001)));
    redraw();
  };
  const play = document.getElementById("play");
  if (A.track) {
    let t0 = null, playing = false;
    const T = A.track.values.length;
    const step = (now) => {
      if (!playing) return;
      if (t0 === null) t0 = now;
      const i = Math.floor((now - t0) / 1000 * A.track.fps) % T;
      A.track.values[i].forEach((v, k) => { beta[k] = v; sliders[k].value = v; });
      draw(orbitCamera());
      requestAnimationFrame(step);
    };
    play.onclick = () => {
      playing = !playing; t0 = null; play.textContent = playing ? "Pause" : "Play track";
      if (playing) requestAnimationFrame(step);
    };
  } else {
    play.disabled = true; play.title = "exported without a track (export --track FILE)";
  }
  draw(orbitCamera());
})();
