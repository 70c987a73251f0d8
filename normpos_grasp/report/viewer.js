// normpos-grasp 3D viewer: plain WebGL 1, no external libraries, no network.
// Reads the scene from <script id="scene-data" type="application/json"> or, in live mode, polls /scene.json.
// Reports render health in #status: data-errors (count), data-nonempty (non-background pixels), data-frames.
"use strict";
(function () {
  const status = document.getElementById("status");
  const errors = [];
  function report(extra) {
    status.dataset.errors = String(errors.length);
    if (extra) { Object.assign(status.dataset, extra); }
    status.textContent = errors.length ? "viewer errors: " + errors.join("; ") : (status.dataset.message || "");
  }
  window.addEventListener("error", function (e) { errors.push(String(e.message)); report(); });
  const consoleError = console.error.bind(console);
  console.error = function () { errors.push(Array.from(arguments).join(" ")); report(); consoleError.apply(null, arguments); };
  report({ nonempty: "0", frames: "0" });

  function bytes(b64) {
    const bin = atob(b64);
    const out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) { out[i] = bin.charCodeAt(i); }
    return out.buffer;
  }

  // ---- 4x4 column-major matrices --------------------------------------------------------------
  function mul(a, b) {
    const o = new Float32Array(16);
    for (let c = 0; c < 4; c++) {
      for (let r = 0; r < 4; r++) {
        let s = 0;
        for (let k = 0; k < 4; k++) { s += a[k * 4 + r] * b[c * 4 + k]; }
        o[c * 4 + r] = s;
      }
    }
    return o;
  }
  function perspective(fovy, aspect, near, far) {
    const f = 1 / Math.tan(fovy / 2), o = new Float32Array(16);
    o[0] = f / aspect; o[5] = f; o[10] = (far + near) / (near - far); o[11] = -1; o[14] = 2 * far * near / (near - far);
    return o;
  }
  function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function norm(a) { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; }
  function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
  function lookAt(eye, target, up) {
    const z = norm(sub(eye, target)), x = norm(cross(up, z)), y = cross(z, x), o = new Float32Array(16);
    o[0] = x[0]; o[4] = x[1]; o[8] = x[2]; o[12] = -dot(x, eye);
    o[1] = y[0]; o[5] = y[1]; o[9] = y[2]; o[13] = -dot(y, eye);
    o[2] = z[0]; o[6] = z[1]; o[10] = z[2]; o[14] = -dot(z, eye);
    o[15] = 1;
    return o;
  }

  // ---- GL setup -------------------------------------------------------------------------------
  const canvas = document.getElementById("view");
  const gl = canvas.getContext("webgl", { preserveDrawingBuffer: true, antialias: true });
  if (!gl) { errors.push("WebGL is not available in this browser"); report(); return; }
  function shader(type, src) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) { throw new Error(gl.getShaderInfoLog(s)); }
    return s;
  }
  function program(vs, fs) {
    const p = gl.createProgram();
    gl.attachShader(p, shader(gl.VERTEX_SHADER, vs)); gl.attachShader(p, shader(gl.FRAGMENT_SHADER, fs));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) { throw new Error(gl.getProgramInfoLog(p)); }
    return p;
  }
  const meshProg = program(
    "attribute vec3 p; attribute vec3 n; uniform mat4 mvp; varying vec3 vn;" +
    "void main() { gl_Position = mvp * vec4(p, 1.0); vn = n; }",
    "precision mediump float; uniform vec3 color; uniform float alpha; varying vec3 vn;" +
    "void main() { vec3 l = normalize(vec3(0.4, 0.3, 1.0)); float d = abs(dot(normalize(vn), l));" +
    " gl_FragColor = vec4(color * (0.35 + 0.65 * d), alpha); }");
  const pointProg = program(
    "attribute vec3 p; attribute vec3 c; uniform mat4 mvp; uniform float size; varying vec3 vc;" +
    "void main() { gl_Position = mvp * vec4(p, 1.0); gl_PointSize = size; vc = c; }",
    "precision mediump float; varying vec3 vc; void main() { gl_FragColor = vec4(vc, 1.0); }");

  let items = { meshes: [], clouds: [] };
  let center = [0, 0, 0], radius = 1;
  const view = { yaw: -0.9, pitch: 0.6, dist: 2.5, pan: [0, 0, 0] };

  function buffer(data) {
    const b = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, b); gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
    return b;
  }
  function load(scene) {
    for (const m of items.meshes) { gl.deleteBuffer(m.pb); gl.deleteBuffer(m.nb); }
    for (const c of items.clouds) { gl.deleteBuffer(c.pb); gl.deleteBuffer(c.cb); }
    items = { meshes: [], clouds: [] };
    for (const m of scene.meshes) {
      const v = new Float32Array(bytes(m.positions)), f = new Uint32Array(bytes(m.indices));
      const pos = new Float32Array(f.length * 3), nrm = new Float32Array(f.length * 3);
      for (let t = 0; t < f.length; t += 3) {
        const a = [v[f[t] * 3], v[f[t] * 3 + 1], v[f[t] * 3 + 2]];
        const b = [v[f[t + 1] * 3], v[f[t + 1] * 3 + 1], v[f[t + 1] * 3 + 2]];
        const c = [v[f[t + 2] * 3], v[f[t + 2] * 3 + 1], v[f[t + 2] * 3 + 2]];
        const n = norm(cross(sub(b, a), sub(c, a)));
        [a, b, c].forEach(function (q, k) { pos.set(q, (t + k) * 3); nrm.set(n, (t + k) * 3); });
      }
      items.meshes.push({ pb: buffer(pos), nb: buffer(nrm), count: f.length, color: m.color, alpha: m.opacity });
    }
    for (const c of scene.clouds) {
      const p = new Float32Array(bytes(c.positions)), col = new Float32Array(bytes(c.colors));
      items.clouds.push({ pb: buffer(p), cb: buffer(col), count: p.length / 3 });
    }
    const lo = scene.bounds[0], hi = scene.bounds[1];
    center = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2];
    radius = Math.max(0.2, Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2);
    view.dist = radius * 2.6;
  }
  function attrib(prog, name, buf) {
    const loc = gl.getAttribLocation(prog, name);
    gl.bindBuffer(gl.ARRAY_BUFFER, buf); gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, 3, gl.FLOAT, false, 0, 0);
    return loc;
  }
  let frames = 0;
  function draw() {
    const w = canvas.clientWidth || canvas.width, h = canvas.clientHeight || canvas.height;
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.clearColor(0.96, 0.96, 0.97, 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    const target = [center[0] + view.pan[0], center[1] + view.pan[1], center[2] + view.pan[2]];
    const eye = [target[0] + view.dist * Math.cos(view.pitch) * Math.cos(view.yaw),
      target[1] + view.dist * Math.cos(view.pitch) * Math.sin(view.yaw),
      target[2] + view.dist * Math.sin(view.pitch)];
    const mvp = mul(perspective(0.8, canvas.width / canvas.height, radius * 0.01, radius * 20), lookAt(eye, target, [0, 0, 1]));
    gl.useProgram(meshProg);
    gl.uniformMatrix4fv(gl.getUniformLocation(meshProg, "mvp"), false, mvp);
    const passes = [items.meshes.filter(function (m) { return m.alpha >= 1; }), items.meshes.filter(function (m) { return m.alpha < 1; })];
    passes.forEach(function (list, transparent) {
      if (transparent) { gl.enable(gl.BLEND); gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA); gl.depthMask(false); }
      for (const m of list) {
        const lp = attrib(meshProg, "p", m.pb), ln = attrib(meshProg, "n", m.nb);
        gl.uniform3fv(gl.getUniformLocation(meshProg, "color"), m.color);
        gl.uniform1f(gl.getUniformLocation(meshProg, "alpha"), m.alpha);
        gl.drawArrays(gl.TRIANGLES, 0, m.count);
        gl.disableVertexAttribArray(lp); gl.disableVertexAttribArray(ln);
      }
      gl.disable(gl.BLEND); gl.depthMask(true);
    });
    gl.useProgram(pointProg);
    gl.uniformMatrix4fv(gl.getUniformLocation(pointProg, "mvp"), false, mvp);
    gl.uniform1f(gl.getUniformLocation(pointProg, "size"), 2.0);
    for (const c of items.clouds) {
      const lp = attrib(pointProg, "p", c.pb), lc = attrib(pointProg, "c", c.cb);
      gl.drawArrays(gl.POINTS, 0, c.count);
      gl.disableVertexAttribArray(lp); gl.disableVertexAttribArray(lc);
    }
    frames += 1;
    const px = new Uint8Array(canvas.width * canvas.height * 4);
    gl.readPixels(0, 0, canvas.width, canvas.height, gl.RGBA, gl.UNSIGNED_BYTE, px);
    let nonempty = 0;
    for (let i = 0; i < px.length; i += 4) {
      if (Math.abs(px[i] - 245) > 6 || Math.abs(px[i + 1] - 245) > 6 || Math.abs(px[i + 2] - 247) > 6) { nonempty++; }
    }
    report({ nonempty: String(nonempty), frames: String(frames) });
  }

  // ---- interaction ----------------------------------------------------------------------------
  let drag = null;
  canvas.addEventListener("mousedown", function (e) { drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey }; });
  window.addEventListener("mouseup", function () { drag = null; });
  window.addEventListener("mousemove", function (e) {
    if (!drag) { return; }
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) {
      const s = view.dist * 0.002;
      view.pan[0] += s * (dx * Math.sin(view.yaw)); view.pan[1] -= s * (dx * Math.cos(view.yaw)); view.pan[2] += s * dy;
    } else {
      view.yaw -= dx * 0.01; view.pitch = Math.max(-1.5, Math.min(1.5, view.pitch + dy * 0.01));
    }
    draw();
  });
  canvas.addEventListener("wheel", function (e) { e.preventDefault(); view.dist *= Math.exp(e.deltaY * 0.001); draw(); }, { passive: false });

  // ---- data -----------------------------------------------------------------------------------
  const embedded = document.getElementById("scene-data");
  if (embedded && embedded.textContent.trim().length > 2) {
    load(JSON.parse(embedded.textContent));
    draw();
  }
  if (window.NORMPOS_LIVE) {
    let version = null;
    const stateBox = document.getElementById("arm-state");
    const poll = function () {
      fetch("/scene.json?since=" + encodeURIComponent(version || "")).then(function (r) { return r.json(); }).then(function (s) {
        if (s.version !== version && s.scene) { version = s.version; load(s.scene); }
        if (stateBox && s.state) { stateBox.textContent = JSON.stringify(s.state, null, 1); }
        draw();
      }).catch(function (err) { status.dataset.message = "live view: " + err; report(); });
    };
    poll();
    setInterval(poll, 500);
  }
})();
