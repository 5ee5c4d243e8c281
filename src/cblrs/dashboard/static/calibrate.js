// cblrs calibration page: a camera frame beside the site map; click pairs, see the fit live,
// save to the site file and look at the rendered reference. window.cblrsCalibrate exposes
// the coordinate transforms and the last fit, so a test can click exact points.
"use strict";

const cal = {
  scene: null, cameras: [], camera: null, imageSize: null, frame: null, map: null,
  pairs: [], pendingPixel: null, pendingWorld: null, result: null, error: null,
  fitting: 0, fits: 0, saved: null,
};
window.cblrsCalibrate = cal;

const $c = (id) => document.getElementById(id);

// ------------------------------------------------------------------ frame canvas
const frameCanvas = $c("frame");

function frameTransform() {
  const box = frameCanvas.getBoundingClientRect();
  const [width, height] = cal.imageSize || [1920, 1080];
  const scale = Math.min(box.width / width, box.height / height);
  return { scale, x: (box.width - width * scale) / 2, y: (box.height - height * scale) / 2 };
}
cal.frameToScreen = (u, v) => {
  const t = frameTransform();
  const box = frameCanvas.getBoundingClientRect();
  return [box.left + t.x + u * t.scale, box.top + t.y + v * t.scale];
};
cal.worldToScreen = (x, y) => {
  const box = $c("sitemap").getBoundingClientRect();
  const [sx, sy] = cal.map.toScreen(x, y);
  return [box.left + sx, box.top + sy];
};

function drawFrame() {
  const ratio = window.devicePixelRatio || 1;
  const box = frameCanvas.getBoundingClientRect();
  frameCanvas.width = Math.round(box.width * ratio);
  frameCanvas.height = Math.round(box.height * ratio);
  const ctx = frameCanvas.getContext("2d");
  ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
  ctx.fillStyle = "#0f1419";
  ctx.fillRect(0, 0, box.width, box.height);
  const t = frameTransform();
  const [width, height] = cal.imageSize || [1920, 1080];
  if (cal.frame) ctx.drawImage(cal.frame, t.x, t.y, width * t.scale, height * t.scale);
  else {
    ctx.fillStyle = "#1c242e";
    ctx.fillRect(t.x, t.y, width * t.scale, height * t.scale);
    ctx.fillStyle = "#8592a3";
    ctx.fillText("no frame: open one from a file", t.x + 10, t.y + 20);
  }
  const perPoint = cal.result ? cal.result.per_point : [];
  cal.pairs.forEach((pair, index) => {
    const px = t.x + pair.u * t.scale, py = t.y + pair.v * t.scale;
    const point = perPoint[index];
    if (point && point.projected) {
      const [qu, qv] = point.projected;
      ctx.strokeStyle = point.inlier ? "#3ecf8e" : "#ff6b6b";
      ctx.beginPath(); ctx.moveTo(px, py); ctx.lineTo(t.x + qu * t.scale, t.y + qv * t.scale);
      ctx.stroke();
      ctx.strokeRect(t.x + qu * t.scale - 3, t.y + qv * t.scale - 3, 6, 6);
    }
    marker(ctx, px, py, index + 1);
  });
  if (cal.pendingPixel) marker(ctx, t.x + cal.pendingPixel[0] * t.scale,
    t.y + cal.pendingPixel[1] * t.scale, "?");
}

function marker(ctx, x, y, label) {
  ctx.strokeStyle = "#f5b942";
  ctx.lineWidth = 2;
  ctx.beginPath();
  ctx.moveTo(x - 7, y); ctx.lineTo(x + 7, y); ctx.moveTo(x, y - 7); ctx.lineTo(x, y + 7);
  ctx.stroke();
  ctx.fillStyle = "#ffe2a3";
  ctx.font = "12px system-ui";
  ctx.fillText(String(label), x + 6, y - 6);
}

frameCanvas.addEventListener("click", (event) => {
  const box = frameCanvas.getBoundingClientRect();
  const t = frameTransform();
  const u = (event.clientX - box.left - t.x) / t.scale;
  const v = (event.clientY - box.top - t.y) / t.scale;
  const [width, height] = cal.imageSize || [1920, 1080];
  if (u < 0 || v < 0 || u > width || v > height) return;
  cal.pendingPixel = [u, v];
  completePair();
});

// ------------------------------------------------------------------ map canvas
function drawMap() {
  const view = cal.map;
  if (view.dirtyStatic) view.drawStatic();
  const ctx = view.canvas.getContext("2d");
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.drawImage(view.staticLayer, 0, 0);
  ctx.setTransform(view.ratio, 0, 0, view.ratio, 0, 0);
  view.drawPlaces(ctx, {}, {}, 0);
  cal.pairs.forEach((pair, index) => {
    const [sx, sy] = view.toScreen(pair.x, pair.y);
    marker(ctx, sx, sy, index + 1);
  });
  if (cal.pendingWorld) {
    const [sx, sy] = view.toScreen(cal.pendingWorld[0], cal.pendingWorld[1]);
    marker(ctx, sx, sy, "?");
  }
}

// ------------------------------------------------------------------ pairs and fits
function completePair() {
  if (cal.pendingPixel && cal.pendingWorld) {
    cal.pairs.push({ u: cal.pendingPixel[0], v: cal.pendingPixel[1],
      x: cal.pendingWorld[0], y: cal.pendingWorld[1], name: `p${cal.pairs.length + 1}` });
    cal.pendingPixel = cal.pendingWorld = null;
    refit();
  }
  redraw();
}

function request() {
  const focal = $c("focal").value;
  return { camera: cal.camera, image_size: cal.imageSize, points: cal.pairs,
    model: $c("model").value, focal_px: focal ? Number(focal) : null, unit: "metres" };
}

async function refit() {
  cal.error = null;
  if (cal.pairs.length < 4) {
    cal.result = null;
    render();
    return;
  }
  const ticket = ++cal.fitting;
  try {
    const result = await Cblrs.fetchJSON("/api/calibrate/fit", {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify(request()),
    });
    if (ticket !== cal.fitting) return;  // a newer fit is on its way
    cal.result = result;
  } catch (error) {
    if (ticket !== cal.fitting) return;
    cal.result = null;
    cal.error = error.message;
  }
  cal.fits += 1;
  render();
}

function render() {
  const { el, fill } = Cblrs;
  const result = cal.result;
  const summary = $c("summary");
  if (cal.error) fill(summary, [el("span", { className: "error" }, cal.error)]);
  else if (!result) summary.textContent = `${cal.pairs.length} pairs: four or more give a fit.`;
  else {
    const position = result.position ? result.position.map((v) => v.toFixed(2)).join(", ") : "–";
    fill(summary, [
      el("span", { className: "ok" }, `model ${result.model}`), " · RMS ",
      el("b", { id: "rms" }, result.rms_px.toFixed(2)),
      ` px · median ${result.median_error_m.toFixed(3)} m` +
      ` · max ${result.max_error_m.toFixed(3)} m · focal ${result.focal_px ? result.focal_px.toFixed(0) : "–"} px` +
      ` · camera at (${position})` + predicted(result.predicted_error),
      ...result.warnings.map((warning) => el("div", { className: "error" }, warning)),
    ]);
  }
  const perPoint = result ? result.per_point : [];
  fill($c("pairs").querySelector("tbody"), cal.pairs.map((pair, index) => {
    const point = perPoint[index];
    return el("tr", {}, el("td", {}, pair.name),
      el("td", {}, `${pair.u.toFixed(1)}, ${pair.v.toFixed(1)}`),
      el("td", {}, `${pair.x.toFixed(2)}, ${pair.y.toFixed(2)}`),
      el("td", { className: "error-px" }, point ? point.error_px.toFixed(2) : "–"),
      el("td", {}, point && point.error_m !== null ? point.error_m.toFixed(3) : "–"),
      el("td", {}, point && !point.inlier ? "outlier" : ""),
      el("td", {}, el("button", { className: "mode", type: "button", dataset: { remove: index } },
        "×")));
  }));
  $c("save").disabled = !result;
  redraw();
}

// The fit's predicted ground error between the points (from its covariance), when known.
function predicted(coverage) {
  if (!coverage || coverage.median_m === null || coverage.median_m === undefined) return "";
  const share = (100 * coverage.share_over_limit).toFixed(0);
  return ` · predicted ground error median ${coverage.median_m.toFixed(3)} m` +
    ` (${share} % of the view over ${coverage.limit_m.toFixed(2)} m)`;
}

function redraw() { drawFrame(); if (cal.map) drawMap(); }

document.addEventListener("click", (event) => {
  const index = event.target.getAttribute && event.target.getAttribute("data-remove");
  if (index !== null && index !== undefined) {
    cal.pairs.splice(Number(index), 1);
    refit();
  }
});
$c("undo").onclick = () => {
  if (cal.pendingPixel || cal.pendingWorld) cal.pendingPixel = cal.pendingWorld = null;
  else cal.pairs.pop();
  refit();
};
$c("clear").onclick = () => { cal.pairs = []; cal.pendingPixel = cal.pendingWorld = null; refit(); };
$c("model").onchange = refit;
$c("focal").onchange = refit;
$c("save").onclick = async () => {
  $c("saved").textContent = "saving…";
  try {
    const saved = await Cblrs.fetchJSON("/api/calibrate/save", {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify(request()),
    });
    cal.saved = saved;
    Cblrs.fill($c("saved"), [Cblrs.el("span", { className: "ok" }, `saved to ${saved.site}`),
      ` (previous file: ${saved.backup}); reference ${saved.reference}`]);
    const image = $c("reference");
    image.onload = () => { cal.referenceLoaded = true; };
    image.src = `/api/calibrate/reference/${encodeURIComponent(cal.camera)}?t=${Date.now()}`;
    image.classList.remove("hidden");
  } catch (error) {
    Cblrs.fill($c("saved"), [Cblrs.el("span", { className: "error" }, error.message)]);
  }
};
$c("frame-file").onchange = (event) => {
  const file = event.target.files[0];
  if (!file) return;
  // The frame stays in this browser: only clicked coordinates go to the server.
  const image = new Image();
  image.onload = () => {
    cal.frame = image;
    cal.imageSize = [image.naturalWidth, image.naturalHeight];
    $c("frame-note").textContent = `(${file.name}, ${image.naturalWidth}×${image.naturalHeight})`;
    redraw();
  };
  image.src = URL.createObjectURL(file);
};

function chooseCamera(name) {
  const camera = cal.cameras.find((item) => item.name === name);
  cal.camera = name;
  cal.imageSize = camera.image_size;
  cal.pairs = camera.points_unit === "metres" ? camera.points.map((point, index) =>
    ({ ...point, name: point.name || `p${index + 1}` })) : [];
  cal.frame = null;
  cal.result = null;
  $c("frame-note").textContent = camera.frame ? "" : "(no frame on the server)";
  if (camera.frame) {
    const image = new Image();
    image.onload = () => {
      cal.frame = image;
      cal.imageSize = cal.imageSize || [image.naturalWidth, image.naturalHeight];
      cal.frameLoaded = true;
      redraw();
    };
    image.src = `/api/calibrate/frame/${encodeURIComponent(name)}`;
  }
  refit();
}

Cblrs.loadSession()
  .then(() => Promise.all([Cblrs.fetchJSON("/api/site"), Cblrs.fetchJSON("/api/calibrate/cameras")]))
  .then(([scene, data]) => {
    cal.scene = scene;
    cal.cameras = data.cameras;
    $c("site-name").textContent = `calibration · ${scene.name}`;
    const mapCanvas = $c("sitemap");
    cal.map = new Cblrs.MapView(mapCanvas, scene);
    mapCanvas.addEventListener("click", (event) => {
      const box = mapCanvas.getBoundingClientRect();
      cal.pendingWorld = cal.map.toWorld(event.clientX - box.left, event.clientY - box.top);
      completePair();
    });
    window.addEventListener("resize", () => { cal.map.resize(); redraw(); });
    Cblrs.fill($c("camera"), data.cameras.map((camera) =>
      Cblrs.el("option", { value: camera.name }, camera.name)));
    $c("camera").onchange = (event) => chooseCamera(event.target.value);
    const wanted = new URLSearchParams(location.search).get("camera");
    chooseCamera(wanted && data.cameras.some((c) => c.name === wanted) ? wanted : data.cameras[0].name);
    $c("camera").value = cal.camera;
    cal.ready = true;
  })
  .catch((error) => {
    Cblrs.fill($c("summary"), [Cblrs.el("span", { className: "error" }, error.message)]);
  });
