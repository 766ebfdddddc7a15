// plantsplat report viewer: orbit/zoom a Gaussian splat (Spark + three.js) and a point cloud.
// A classic script (no modules, no fetch) so that report.html works when opened from file://.
// Data comes from <script type="application/octet-stream"> blocks holding base64:
//   #splat-data   .splat records, 32 bytes per Gaussian (see plantsplat/report/splat.py)
//   #points-xyz   float32 little-endian [N, 3];  #points-rgb   uint8 [N, 3]
// and #viewer-config (JSON): {center: [3], radius, background, splat: bool, points: bool, mode,
// splat_count, preview_count}.
// window.plantsplatViewer exposes state for tests and benchmarks: state ('loading' | 'ready' | 'error'),
// error, firstContentMs (first frame with the model drawn, ms since navigation start), setMode(mode),
// rendered() -> Promise (next frame presented), setAdaptive(bool) (dynamic resolution while moving),
// orbit(frames) -> Promise<{fps, msPerFrame, medianFps, medianMsPerFrame, maxMsPerFrame, frames, pixelRatio,
// preview}>.
(function () {
  "use strict";

  var api = { state: "loading", error: null, firstContentMs: null, readyMs: null, mode: null };
  window.plantsplatViewer = api;

  function fail(msg) {
    api.state = "error";
    api.error = msg;
    var box = document.getElementById("viewer-message");
    if (box) { box.textContent = msg; box.style.display = "block"; }
  }

  function b64ToBytes(text) {
    var s = text.replace(/\s+/g, "");
    if (typeof Uint8Array.fromBase64 === "function") return Uint8Array.fromBase64(s);
    var bin = atob(s);
    var out = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }

  function dataBlock(id) {
    var el = document.getElementById(id);
    return el ? b64ToBytes(el.textContent) : null;
  }

  function webglAvailable() {
    try {
      var c = document.createElement("canvas");
      return !!c.getContext("webgl2");
    } catch (e) { return false; }
  }

  function init() {
    var cfgEl = document.getElementById("viewer-config");
    var canvas = document.getElementById("viewer-canvas");
    if (!cfgEl || !canvas) return;  // report without a 3D section
    var cfg = JSON.parse(cfgEl.textContent);
    var L = window.PlantsplatViewerLib;
    if (!L) { fail("The 3D viewer library did not load; the report file may be truncated."); return; }
    if (!webglAvailable()) { fail("WebGL 2 is not available in this browser, so the 3D view is disabled."); return; }
    var THREE = L.THREE;

    var renderer = new THREE.WebGLRenderer({ canvas: canvas, antialias: false, preserveDrawingBuffer: true });
    renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    var scene = new THREE.Scene();
    var bg = new THREE.Color(cfg.background || "#202124");
    scene.background = bg;

    var center = new THREE.Vector3(cfg.center[0], cfg.center[1], cfg.center[2]);
    var radius = Math.max(cfg.radius, 1e-3);
    var camera = new THREE.PerspectiveCamera(45, 1, radius * 0.01, radius * 200);
    camera.up.set(0, 0, 1);  // world frame: z up (centimetres)
    function homeView() {
      var az = -Math.PI / 2.6, el = Math.PI / 7, dist = 0.85 * radius / Math.sin((camera.fov / 2) * Math.PI / 180);  // about the bounding sphere
      camera.position.set(center.x + dist * Math.cos(el) * Math.cos(az),
                          center.y + dist * Math.cos(el) * Math.sin(az),
                          center.z + dist * Math.sin(el));
      camera.lookAt(center);
    }
    homeView();
    var controls = new L.OrbitControls(camera, canvas);
    controls.target.copy(center);
    controls.update();

    // ground grid on z = 0 with 5 cm cells, for scale
    var cells = Math.max(2, Math.ceil((radius * 2.5) / 5));
    var grid = new THREE.GridHelper(cells * 5, cells, 0x666666, 0x3a3a3a);
    grid.rotation.x = Math.PI / 2;
    scene.add(grid);

    var needsRender = true, autoRotate = false, interacting = false, splat = null, points = null, spark = null;
    var preview = null, usePreview = false, previewCount = 0, memory = null;  // preview: the most visible Gaussians, drawn while moving when slow
    var orbitJob = null, renderWaiters = [];
    function requestRender() { needsRender = true; }

    // Dynamic resolution: while the view moves, drop the pixel ratio when frames take longer than
    // ~45 ms (software WebGL, weak GPUs), raise it back when they are fast; full resolution when still.
    var fullRatio = Math.min(window.devicePixelRatio || 1, 2), ratio = fullRatio, minRatio = fullRatio * 0.35;
    var lastFrameT = null, frameEma = null, lastMoveT = 0, adaptive = cfg.adaptive_resolution !== false;
    api.pixelRatio = function () { return ratio; };
    function setRatio(r) {
      if (Math.abs(r - ratio) < 1e-3) return;
      ratio = r;
      renderer.setPixelRatio(ratio);
    }

    function resize() {
      var w = canvas.clientWidth || 800, h = canvas.clientHeight || 500;
      renderer.setSize(w, h, false);
      camera.aspect = w / h;
      camera.updateProjectionMatrix();
      requestRender();
    }
    window.addEventListener("resize", resize);
    renderer.setPixelRatio(ratio);
    resize();

    // share of sampled pixels that differ from the background (used once, to time the first drawn frame)
    var probe = null;
    function checkContent() {
      var gl = renderer.getContext();
      var w = gl.drawingBufferWidth, h = gl.drawingBufferHeight;
      if (!probe || probe.length !== w * h * 4) probe = new Uint8Array(w * h * 4);
      gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, probe);
      var r = Math.round(bg.r * 255), g = Math.round(bg.g * 255), b = Math.round(bg.b * 255), n = 0;
      for (var i = 0; i < probe.length; i += 16) {
        if (Math.abs(probe[i] - r) + Math.abs(probe[i + 1] - g) + Math.abs(probe[i + 2] - b) > 60) n++;
      }
      return n / (probe.length / 16);
    }

    // Preview for slow WebGL (software rendering): the most visible Gaussians (records are stored most
    // visible first, so a prefix) with a Spark level-of-detail tree, so the number drawn while moving can
    // be cut to fit a frame budget. Built after the first full frame is on screen.
    function buildPreview() {
      var n = cfg.splat_count || 0, k = Math.min(n, cfg.preview_count || 12000);
      if (!cfg.splat || !adaptive || n < 2 * k || preview) return;
      var p = new L.SplatMesh({ fileBytes: dataBlock("splat-data").subarray(0, k * 32), fileType: "splat", lod: true });
      p.visible = false;
      scene.add(p);
      p.initialized.then(function () { preview = p; previewCount = k; spark.lodSplatCount = k; api.previewCount = k; });
    }

    var zAxis = new THREE.Vector3(0, 0, 1);
    function turn(angle) {
      var off = camera.position.clone().sub(controls.target);
      off.applyAxisAngle(zAxis, angle);
      camera.position.copy(controls.target).add(off);
      camera.lookAt(controls.target);
    }

    function frame(now) {
      var moving = autoRotate || interacting || orbitJob !== null;
      if (autoRotate) turn(0.01);
      if (orbitJob) {
        if (orbitJob.t0 === null) orbitJob.t0 = now;
        else turn((2 * Math.PI) / orbitJob.frames);
      }
      if (moving) { needsRender = true; lastMoveT = now; }
      if (moving && lastFrameT === null && adaptive && memory) {
        // motion starts again: resume at the settings the last motion settled on
        setRatio(memory.ratio); usePreview = memory.preview && !!preview; applyVisibility();
      }
      if (adaptive && lastFrameT !== null && moving) {
        var dt = now - lastFrameT;
        frameEma = frameEma === null ? dt : 0.7 * frameEma + 0.3 * dt;
        if (frameEma > 150) {
          // far too slow (software WebGL): preview subset and half the resolution at once, then fewer
          // preview splats (Spark's level-of-detail budget)
          if (preview && !usePreview) { usePreview = true; applyVisibility(); }
          else if (usePreview && ratio <= minRatio) spark.lodSplatCount = Math.max(1000, Math.round(spark.lodSplatCount * 0.4));
          setRatio(Math.max(minRatio, ratio * 0.5));
          frameEma = null;
        } else if (frameEma > 45) {
          // too slow: lower the resolution to half, then draw the preview subset, then lower further
          if (ratio > fullRatio * 0.5) setRatio(Math.max(fullRatio * 0.5, ratio * 0.75));
          else if (preview && !usePreview) { usePreview = true; applyVisibility(); frameEma = null; }
          else if (ratio > minRatio) setRatio(Math.max(minRatio, ratio * 0.75));
          else if (usePreview && spark.lodSplatCount > 1000) { spark.lodSplatCount = Math.round(spark.lodSplatCount * 0.6); frameEma = null; }
        } else if (frameEma < 22 && usePreview && spark.lodSplatCount < previewCount) {
          spark.lodSplatCount = Math.min(previewCount, Math.round(spark.lodSplatCount / 0.7));
        } else if (frameEma < 22 && ratio < fullRatio) {
          setRatio(Math.min(fullRatio, ratio / 0.85));
        } else if (frameEma < 12 && usePreview) {
          usePreview = false; applyVisibility(); frameEma = null;
        }
      }
      if (!moving && (ratio !== fullRatio || usePreview) && now - lastMoveT > 250) {
        memory = { ratio: ratio, preview: usePreview };
        setRatio(fullRatio); usePreview = false; applyVisibility(); frameEma = null; needsRender = true;
      }
      lastFrameT = moving ? now : null;
      if (needsRender) {
        needsRender = false;
        renderer.render(scene, camera);
        if (api.state === "ready" && api.firstContentMs === null && checkContent() > 0.002) {
          api.firstContentMs = performance.now();
          setTimeout(buildPreview, 300);
        }
        var waiters = renderWaiters;
        renderWaiters = [];
        for (var i = 0; i < waiters.length; i++) requestAnimationFrame(waiters[i]);
      }
      if (orbitJob && orbitJob.t0 !== null) {
        orbitJob.times.push(now - (orbitJob.last === null ? orbitJob.t0 : orbitJob.last));
        orbitJob.last = now;
      }
      if (orbitJob && orbitJob.t0 !== null && ++orbitJob.done >= orbitJob.frames) {
        var job = orbitJob, ms = (performance.now() - job.t0) / job.frames;
        var sorted = job.times.slice(1).sort(function (a, b) { return a - b; });
        var median = sorted.length ? sorted[Math.floor(sorted.length / 2)] : ms;
        orbitJob = null;
        job.resolve({ frames: job.frames, msPerFrame: ms, fps: 1000 / ms, medianMsPerFrame: median, medianFps: 1000 / median,
                     maxMsPerFrame: job.times.length ? Math.max.apply(null, job.times) : ms,
                     pixelRatio: ratio, fullPixelRatio: fullRatio,
                     preview: usePreview ? spark.lodSplatCount : null });
      }
      requestAnimationFrame(frame);
    }

    controls.addEventListener("change", requestRender);
    controls.addEventListener("start", function () { interacting = true; });
    controls.addEventListener("end", function () { interacting = false; });
    api.three = { renderer: renderer, scene: scene, camera: camera, controls: controls };

    function applyVisibility() {
      var mode = api.mode, showSplat = mode === "splat" || mode === "both";
      if (splat) splat.visible = showSplat && !(usePreview && preview);
      if (preview) preview.visible = showSplat && usePreview;
      if (spark) spark.visible = showSplat;  // Spark draws its splat buffer unless hidden itself
      if (points) points.visible = mode === "points" || mode === "both";
      requestRender();
    }
    function setMode(mode) {
      api.mode = mode;
      applyVisibility();
      var buttons = document.querySelectorAll("[data-viewer-mode]");
      for (var i = 0; i < buttons.length; i++) {
        buttons[i].classList.toggle("active", buttons[i].getAttribute("data-viewer-mode") === mode);
      }
    }
    api.setMode = setMode;
    api.home = function () { homeView(); controls.target.copy(center); controls.update(); requestRender(); };
    api.setAutoRotate = function (on) { autoRotate = !!on; requestRender(); };
    api.setAdaptive = function (on) {
      adaptive = !!on;
      if (!adaptive) { setRatio(fullRatio); usePreview = false; memory = null; applyVisibility(); }
    };
    // resolves once the next frame has been rendered and presented
    api.rendered = function () { return new Promise(function (res) { renderWaiters.push(res); requestRender(); }); };
    // turn the camera a full circle in `frames` displayed frames; resolves with the frame rate
    api.orbit = function (frames) {
      return new Promise(function (resolve) {
        orbitJob = { frames: frames || 60, done: 0, t0: null, last: null, times: [], resolve: resolve };
      });
    };

    var buttons = document.querySelectorAll("[data-viewer-mode]");
    for (var i = 0; i < buttons.length; i++) {
      buttons[i].addEventListener("click", function (ev) { setMode(ev.currentTarget.getAttribute("data-viewer-mode")); });
    }
    var homeBtn = document.getElementById("viewer-home");
    if (homeBtn) homeBtn.addEventListener("click", api.home);
    var rotBtn = document.getElementById("viewer-rotate");
    if (rotBtn) rotBtn.addEventListener("click", function () {
      autoRotate = !autoRotate; rotBtn.classList.toggle("active", autoRotate); requestRender();
    });

    var pending = [];
    if (cfg.points) {
      var xyz = dataBlock("points-xyz"), rgb = dataBlock("points-rgb");
      var geom = new THREE.BufferGeometry();
      geom.setAttribute("position", new THREE.BufferAttribute(new Float32Array(xyz.buffer, xyz.byteOffset, xyz.byteLength / 4), 3));
      geom.setAttribute("color", new THREE.BufferAttribute(rgb, 3, true));
      var mat = new THREE.PointsMaterial({ size: cfg.point_size || radius * 0.012, vertexColors: true, sizeAttenuation: true });
      points = new THREE.Points(geom, mat);
      scene.add(points);
    }
    if (cfg.splat) {
      spark = new L.SparkRenderer({ renderer: renderer, onDirty: requestRender });
      scene.add(spark);
      splat = new L.SplatMesh({ fileBytes: dataBlock("splat-data"), fileType: "splat" });
      scene.add(splat);
      pending.push(splat.initialized);
    }
    setMode(cfg.mode || (cfg.splat ? "splat" : "points"));
    requestAnimationFrame(frame);

    Promise.all(pending).then(function () {
      api.state = "ready";
      api.readyMs = performance.now();
      requestRender();
    }, function (err) {
      fail("Could not load the Gaussian splat: " + (err && err.message ? err.message : err));
    });
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
