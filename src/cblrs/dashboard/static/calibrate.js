// cblrs calibration page: a camera frame beside the site map; click pairs (zoomed in where a
// point must be exact, or with the ground point typed), see the fit live, save to the site
// file and look at the rendered reference. window.cblrsCalibrate exposes the coordinate
// transforms and the last fit, so a test can click exact points. Every name and message from
// the server reaches the page as text (textContent), never as markup.
"use strict";

const cal = {
  scene: null, cameras: [], camera: null, imageSize: null, frame: null, map: null,
  pairs: [], pendingPixel: null, pendingWorld: null, result: null, error: null,
  fitting: 0, fits: 0, saved: null,
  // The frame's view: zoom over "whole frame" and the image pixel at the canvas centre.
  frameView: { zoom: 1, centre: null },
  mapZoom: 1,
};
window.cblrsCalibrate = cal;

const $c = (id) => document.getElementById(id);
const MAX_FRAME_ZOOM = 40;
const MAX_MAP_ZOOM = 200;
const WHEEL_STEP = 1.25;
const DRAG_PX = 4;  // a press that moves further pans; a shorter one is a click

function element(tag, text, className) {
  const node = document.createElement(tag);
  if (text !== undefined && text !== null) node.textContent = String(text);
  if (className) node.className = className;
  return node;
}

// ------------------------------------------------------------------ frame canvas
const frameCanvas = $c("frame");

function imageSize() { return cal.imageSize || [1920, 1080]; }

function frameTransform() {
  const box = frameCanvas.getBoundingClientRect();
  const [width, height] = imageSize();
  const fit = Math.min(box.width / width, box.height / height);
  const scale = fit * cal.frameView.zoom;
  const [cu, cv] = cal.frameView.centre || [width / 2, height / 2];
  return { scale, fit, x: box.width / 2 - cu * scale, y: box.height / 2 - cv * scale };
}
cal.frameToScreen = (u, v) => {
  const t = frameTransform();
  const box = frameCanvas.getBoundingClientRect();
  return [box.left + t.x + u * t.scale, box.top + t.y + v * t.scale];
};
cal.screenToFrame = (clientX, clientY) => {
  const t = frameTransform();
  const box = frameCanvas.getBoundingClientRect();
  return [(clientX - box.left - t.x) / t.scale, (clientY - box.top - t.y) / t.scale];
};
cal.worldToScreen = (x, y) => {
  const box = $c("sitemap").getBoundingClientRect();
  const [sx, sy] = cal.map.toScreen(x, y);
  return [box.left + sx, box.top + sy];
};
// Image pixels per screen pixel at the current zoom (below 1: finer than the image).
cal.imagePixelsPerScreenPixel = () => 1 / frameTransform().scale;

// Zoom the frame by `factor` keeping the image point under (clientX, clientY) in place.
cal.zoomFrame = (factor, clientX, clientY) => {
  const [u, v] = cal.screenToFrame(clientX, clientY);
  const zoom = Math.min(MAX_FRAME_ZOOM, Math.max(1, cal.frameView.zoom * factor));
  const box = frameCanvas.getBoundingClientRect();
  const [width, height] = imageSize();
  const scale = Math.min(box.width / width, box.height / height) * zoom;
  cal.frameView.zoom = zoom;
  cal.frameView.centre = zoom === 1 ? null : clampCentre([
    u + (box.width / 2 - (clientX - box.left)) / scale,
    v + (box.height / 2 - (clientY - box.top)) / scale,
  ]);
  redraw();
};

function clampCentre([u, v]) {
  const [width, height] = imageSize();
  return [Math.min(width, Math.max(0, u)), Math.min(height, Math.max(0, v))];
}

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
  const [width, height] = imageSize();
  // Zoomed in, show the image's own pixels (a click then lands on one), not a blur.
  ctx.imageSmoothingEnabled = t.scale < 2;
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
  $c("frame-zoom").textContent = `${cal.frameView.zoom.toFixed(1)}× · 1 screen px = ` +
    `${(1 / t.scale).toFixed(2)} image px`;
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

// Wheel zooms, a drag pans, a press without a drag is a click (on both canvases).
function panAndZoom(canvas, { zoom, pan, click }) {
  let press = null;
  canvas.addEventListener("wheel", (event) => {
    event.preventDefault();
    zoom(event.deltaY < 0 ? WHEEL_STEP : 1 / WHEEL_STEP, event.clientX, event.clientY);
  }, { passive: false });
  canvas.addEventListener("mousedown", (event) => {
    if (event.button === 0) press = { x: event.clientX, y: event.clientY, dragging: false };
  });
  window.addEventListener("mousemove", (event) => {
    if (!press) return;
    const dx = event.clientX - press.x, dy = event.clientY - press.y;
    if (!press.dragging && Math.hypot(dx, dy) < DRAG_PX) return;
    press.dragging = true;
    canvas.classList.add("dragging");
    pan(dx, dy);
    press.x = event.clientX;
    press.y = event.clientY;
  });
  window.addEventListener("mouseup", (event) => {
    if (!press) return;
    const dragged = press.dragging;
    press = null;
    canvas.classList.remove("dragging");
    if (!dragged && event.target === canvas) click(event.clientX, event.clientY);
  });
}

panAndZoom(frameCanvas, {
  zoom: cal.zoomFrame,
  pan: (dx, dy) => {
    if (cal.frameView.zoom === 1) return;
    const t = frameTransform();
    const [width, height] = imageSize();
    const [cu, cv] = cal.frameView.centre || [width / 2, height / 2];
    cal.frameView.centre = clampCentre([cu - dx / t.scale, cv - dy / t.scale]);
    redraw();
  },
  click: (clientX, clientY) => {
    const [u, v] = cal.screenToFrame(clientX, clientY);
    const [width, height] = imageSize();
    if (u < 0 || v < 0 || u > width || v > height) return;
    cal.pendingPixel = [u, v];
    completePair();
  },
});
$c("frame-fit").onclick = () => { cal.frameView = { zoom: 1, centre: null }; redraw(); };

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
  $c("map-zoom").textContent = `${cal.mapZoom.toFixed(1)}× · 1 screen px = ` +
    `${(100 / view.scale).toFixed(1)} cm`;
}

// Zoom the map by `factor` keeping the ground point under (clientX, clientY) in place
// (the shared MapView maps metres to pixels by a scale and an offset: they change here).
cal.zoomMap = (factor, clientX, clientY) => {
  const view = cal.map;
  const box = view.canvas.getBoundingClientRect();
  const px = clientX - box.left, py = clientY - box.top;
  const [x, y] = view.toWorld(px, py);
  const zoom = Math.min(MAX_MAP_ZOOM, Math.max(1, cal.mapZoom * factor));
  if (zoom === 1) { view.resize(); cal.mapZoom = 1; redraw(); return; }
  view.scale *= zoom / cal.mapZoom;
  cal.mapZoom = zoom;
  view.offsetX = px - x * view.scale;
  view.offsetY = py + y * view.scale;
  view.dirtyStatic = true;
  redraw();
};

function setupMap() {
  const mapCanvas = $c("sitemap");
  cal.map = new Cblrs.MapView(mapCanvas, cal.scene);
  panAndZoom(mapCanvas, {
    zoom: cal.zoomMap,
    pan: (dx, dy) => {
      if (cal.mapZoom === 1) return;
      cal.map.offsetX += dx;
      cal.map.offsetY += dy;
      cal.map.dirtyStatic = true;
      redraw();
    },
    click: (clientX, clientY) => {
      const box = mapCanvas.getBoundingClientRect();
      cal.pendingWorld = cal.map.toWorld(clientX - box.left, clientY - box.top);
      completePair();
    },
  });
  $c("map-fit").onclick = () => { cal.map.resize(); cal.mapZoom = 1; redraw(); };
  window.addEventListener("resize", () => { cal.map.resize(); cal.mapZoom = 1; redraw(); });
}

// A ground point typed in metres (exact, as the site plan gives it) instead of clicked.
$c("typed").addEventListener("submit", (event) => {
  event.preventDefault();
  const x = Number($c("typed-x").value), y = Number($c("typed-y").value);
  if ($c("typed-x").value === "" || $c("typed-y").value === "" ||
      !Number.isFinite(x) || !Number.isFinite(y)) return;
  cal.pendingWorld = [x, y];
  completePair();
});

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
    model: $c("model").value, focal_px: focal ? Number(focal) : null, unit: "metres",
    left_handed: $c("left-handed").checked };
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
  const result = cal.result;
  const summary = $c("summary");
  summary.replaceChildren();
  if (cal.error) summary.append(element("span", cal.error, "error"));
  else if (!result) summary.append(`${cal.pairs.length} pairs: four or more give a fit.`);
  else {
    const position = result.position ? result.position.map((v) => v.toFixed(2)).join(", ") : "–";
    const rms = element("b", result.rms_px.toFixed(2));
    rms.id = "rms";
    summary.append(element("span", `model ${result.model}`, "ok"), " · RMS ", rms,
      ` px · median ${result.median_error_m.toFixed(3)} m` +
      ` · max ${result.max_error_m.toFixed(3)} m` +
      ` · focal ${result.focal_px ? result.focal_px.toFixed(0) : "–"} px` +
      ` · camera at (${position})` + predicted(result.predicted_error));
    for (const warning of result.warnings) summary.append(element("div", warning, "error"));
  }
  const perPoint = result ? result.per_point : [];
  const body = $c("pairs").querySelector("tbody");
  body.replaceChildren(...cal.pairs.map((pair, index) => pairRow(pair, index, perPoint[index])));
  $c("save").disabled = !result;
  redraw();
}

// One pair's row: its ground x, y editable (typed corrections refit at once).
function pairRow(pair, index, point) {
  const row = element("tr");
  const ground = element("td");
  for (const key of ["x", "y"]) {
    const input = element("input");
    input.type = "number";
    input.step = "any";
    input.value = String(pair[key]);
    input.dataset.pair = String(index);
    input.dataset.key = key;
    input.title = `${key} of ${pair.name}, metres`;
    input.addEventListener("change", () => {
      const value = Number(input.value);
      if (input.value === "" || !Number.isFinite(value)) { input.value = String(pair[key]); return; }
      pair[key] = value;
      refit();
    });
    ground.append(input, " ");
  }
  const remove = element("button", "×", "mode");
  remove.type = "button";
  remove.addEventListener("click", () => { cal.pairs.splice(index, 1); refit(); });
  const removeCell = element("td");
  removeCell.append(remove);
  row.append(
    element("td", pair.name),
    element("td", `${pair.u.toFixed(1)}, ${pair.v.toFixed(1)}`),
    ground,
    element("td", point ? point.error_px.toFixed(2) : "–", "error-px"),
    element("td", point && point.error_m !== null ? point.error_m.toFixed(3) : "–"),
    element("td", point && !point.inlier ? "outlier" : ""),
    removeCell,
  );
  return row;
}

// The fit's predicted ground error between the points (from its covariance), when known.
function predicted(coverage) {
  if (!coverage || coverage.median_m === null || coverage.median_m === undefined) return "";
  const share = (100 * coverage.share_over_limit).toFixed(0);
  return ` · predicted ground error median ${coverage.median_m.toFixed(3)} m` +
    ` (${share} % of the view over ${coverage.limit_m.toFixed(2)} m)`;
}

function redraw() { drawFrame(); if (cal.map) drawMap(); }

$c("undo").onclick = () => {
  if (cal.pendingPixel || cal.pendingWorld) cal.pendingPixel = cal.pendingWorld = null;
  else cal.pairs.pop();
  refit();
};
$c("clear").onclick = () => { cal.pairs = []; cal.pendingPixel = cal.pendingWorld = null; refit(); };
$c("model").onchange = refit;
$c("focal").onchange = refit;
$c("left-handed").onchange = refit;
$c("save").onclick = async () => {
  const saved = $c("saved");
  saved.textContent = "saving…";
  try {
    const answer = await Cblrs.fetchJSON("/api/calibrate/save", {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify(request()),
    });
    cal.saved = answer;
    saved.replaceChildren(element("span", `saved to ${answer.site}`, "ok"),
      ` (previous file: ${answer.backup}); reference ${answer.reference}`);
    const image = $c("reference");
    image.onload = () => { cal.referenceLoaded = true; };
    image.src = await Cblrs.imageURL(
      `/api/calibrate/reference/${encodeURIComponent(cal.camera)}?t=${Date.now()}`);
    image.classList.remove("hidden");
  } catch (error) {
    saved.replaceChildren(element("span", error.message, "error"));
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
    cal.frameView = { zoom: 1, centre: null };
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
  cal.frameView = { zoom: 1, centre: null };
  $c("left-handed").checked = camera.left_handed === true;
  $c("frame-note").textContent = camera.frame ? "" : "(no frame on the server)";
  if (camera.frame) {
    const image = new Image();
    image.onload = () => {
      cal.frame = image;
      cal.imageSize = cal.imageSize || [image.naturalWidth, image.naturalHeight];
      cal.frameLoaded = true;
      redraw();
    };
    Cblrs.imageURL(`/api/calibrate/frame/${encodeURIComponent(name)}`).then(
      (url) => { image.src = url; },
      (error) => { $c("frame-note").textContent = `(the frame did not load: ${error.message})`; });
  }
  refit();
}

Cblrs.loadSession()
  .then(() => Promise.all([Cblrs.fetchJSON("/api/site"), Cblrs.fetchJSON("/api/calibrate/cameras")]))
  .then(([scene, data]) => {
    cal.scene = scene;
    cal.cameras = data.cameras;
    $c("site-name").textContent = `calibration · ${scene.name}`;
    setupMap();
    const select = $c("camera");
    select.replaceChildren(...data.cameras.map((camera) => {
      const option = element("option", camera.name);
      option.value = camera.name;
      return option;
    }));
    select.onchange = (event) => chooseCamera(event.target.value);
    const wanted = new URLSearchParams(location.search).get("camera");
    chooseCamera(wanted && data.cameras.some((c) => c.name === wanted) ? wanted : data.cameras[0].name);
    select.value = cal.camera;
    cal.ready = true;
  })
  .catch((error) => { $c("summary").replaceChildren(element("span", error.message, "error")); });
