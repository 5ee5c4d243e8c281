// cblrs dashboard: the overview of a site of several planes. Reads the site (every plane's
// places and cameras, in site metres: the planes lie where the site file puts them), then
// the live stream of every plane (/api/stream?plane=all): each plane's tracks with their
// global ids (from the linker), its matcher's live summary and status, the cameras' status,
// the site's counts on the global tracks (plane 0), events and alerts.
// Names from the site file and from the backbone reach the page as text only.
// window.cblrsOverview() exposes what a test reads.
"use strict";

const HOLD_S = 0.4;       // a mark not in its plane's update for longer than this goes
const TRAIL_S = 3.0;
const TRAIL_POINTS = 40;
const STALE_WALL_S = 3.0; // a plane silent this long (wall clock): its marks go
const MAX_EVENTS = 30;
const MAX_TRACK_ROWS = 200;

const $ = (id) => document.getElementById(id);
const dict = () => Object.create(null);

const state = {
  scene: null, view: null, dirty: true, tablesDirty: true, source: null, connected: false,
  tracks: new Map(),          // "plane:track" -> {plane, id, global, x, y, t, trail, cls}
  planes: new Map(),          // plane -> {tracks, zones, lines, live, liveAt, matchers, wall}
  site: null,                 // the linker's live summary (plane 0)
  linkers: dict(), cameras: dict(), events: [], seenEvents: new Set(), alerts: [],
  seenAlerts: new Set(), updates: [], time: null, messages: 0,
};

window.cblrsOverview = () => ({
  connected: state.connected,
  messages: state.messages,
  tracks: [...state.tracks.values()].map((track) => ({
    plane: track.plane, track: track.id, global: track.global === undefined ? null : track.global,
  })),
  planes: Object.fromEntries([...state.planes].map(([plane, row]) => [plane, {
    tracks: row.tracks, zones: row.zones, lines: row.lines,
    matchers: { ...row.matchers }, summaries: row.summaries,
  }])),
  site: state.site,
});

function plane(id) {
  if (!state.planes.has(id)) {
    state.planes.set(id, { tracks: 0, zones: 0, lines: 0, live: null, liveAt: null,
      matchers: dict(), wall: null, summaries: 0 });
  }
  return state.planes.get(id);
}

// ------------------------------------------------------------------ messages
function onTracks(message) {
  const t = message.t;
  if (t === null || t === undefined) return;
  const id = message.plane;
  const globals = message.global || [];
  const seen = new Set();
  message.rows.forEach(([track, x, y, cls], index) => {
    const key = `${id}:${track}`;
    seen.add(key);
    let entry = state.tracks.get(key);
    if (!entry) { entry = { plane: id, id: track, trail: [], cls }; state.tracks.set(key, entry); }
    entry.x = x; entry.y = y; entry.t = t; entry.cls = cls || entry.cls;
    if (globals[index] !== null && globals[index] !== undefined) entry.global = globals[index];
    entry.trail.push([x, y, t]);
  });
  for (const [key, entry] of state.tracks) {
    if (entry.plane !== id) continue;
    if (!seen.has(key) && t - entry.t > HOLD_S) state.tracks.delete(key);
    else {
      while (entry.trail.length && (t - entry.trail[0][2] > TRAIL_S
             || entry.trail.length > TRAIL_POINTS)) entry.trail.shift();
    }
  }
  const row = plane(id);
  row.tracks = message.rows.length;
  row.wall = performance.now();
  if (state.time === null || t > state.time) state.time = t;
  state.updates.push(performance.now());
  state.dirty = true;
  state.tablesDirty = true;
}

function onLive(live) {
  if (live.plane === 0) {
    state.site = live;
  } else {
    const row = plane(live.plane);
    row.live = live;
    row.liveAt = performance.now();
    row.summaries += 1;
    row.zones = live.zones.reduce((total, zone) => total + zone.occupancy, 0);
    row.lines = live.lines.reduce((total, line) => total + line.positive + line.negative, 0);
    for (const camera of live.cameras) {
      state.cameras[camera.camera] = { ...(state.cameras[camera.camera] || {}), ...camera,
        plane: live.plane };
    }
  }
  state.tablesDirty = true;
}

function onMessage(message) {
  state.messages += 1;
  switch (message.type) {
    case "tracks": onTracks(message); break;
    case "live": onLive(message); break;
    case "matcher":
      if (message.plane === 0) state.linkers[message.matcher] = message.online;
      else plane(message.plane).matchers[message.matcher] = message.online;
      state.tablesDirty = true;
      break;
    case "status":
      state.cameras[message.camera] = { ...(state.cameras[message.camera] || {}),
        camera: message.camera, online: message.online, plane: message.plane };
      state.tablesDirty = true;
      break;
    case "event": {
      const key = `${message.plane}\u0000${message.key}`;
      if (state.seenEvents.has(key)) break;
      state.seenEvents.add(key);
      state.events.unshift(message);
      state.events.sort((a, b) => b.timestamp - a.timestamp);
      state.events.length = Math.min(state.events.length, MAX_EVENTS);
      state.tablesDirty = true;
      break;
    }
    case "alert": {
      const key = `${message.plane}\u0000${message.episode}\u0000${message.state}`;
      if (state.seenAlerts.has(key)) break;
      state.seenAlerts.add(key);
      state.alerts.unshift(message);
      state.alerts.length = Math.min(state.alerts.length, MAX_EVENTS);
      state.tablesDirty = true;
      break;
    }
    default: break;
  }
}

function connect() {
  if (state.source) state.source.close();
  state.source = Cblrs.eventStream("/api/stream?plane=all", {
    onopen: () => { state.connected = true; setConnection(true); },
    onerror: () => { state.connected = false; setConnection(false); Cblrs.checkSession(); },
    onmessage: (message) => onMessage(JSON.parse(message.data)),
  });
}

function setConnection(ok) {
  $("connection").className = "pill " + (ok ? "on" : "off");
  $("connection").textContent = ok ? "live" : "offline";
}

function showNotice(text) {
  $("notice").textContent = text;
  $("notice").classList.remove("hidden");
}

// ------------------------------------------------------------------ drawing
function draw() {
  const view = state.view;
  if (view.dirtyStatic) view.drawStatic();
  const ctx = view.canvas.getContext("2d");
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.drawImage(view.staticLayer, 0, 0);
  ctx.setTransform(view.ratio, 0, 0, view.ratio, 0, 0);
  view.drawPlaces(ctx, {}, null, performance.now());
  const trails = $("trails").checked;
  const labels = state.tracks.size <= 60;
  ctx.lineWidth = 2;
  for (const track of state.tracks.values()) {
    // One colour per global id when the linker named one: the same person on two planes.
    const colour = track.global === undefined ? track.plane * 7919 + track.id : track.global;
    if (trails && track.trail.length > 1) {
      ctx.strokeStyle = Cblrs.idColour(colour, 0.55);
      ctx.beginPath();
      track.trail.forEach(([x, y], index) => {
        const [sx, sy] = view.toScreen(x, y);
        if (index === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
      });
      ctx.stroke();
    }
    const [sx, sy] = view.toScreen(track.x, track.y);
    ctx.fillStyle = Cblrs.idColour(colour);
    ctx.beginPath();
    ctx.arc(sx, sy, track.cls && track.cls !== "person" ? 6 : 4.5, 0, 2 * Math.PI);
    ctx.fill();
    if (labels) {
      ctx.fillStyle = "#e8edf3";
      ctx.font = "10px system-ui";
      ctx.fillText(`P${track.plane} ${Cblrs.trackLabel(track.id, track.global)}`, sx + 6, sy - 5);
    }
  }
}

function ageText(since) {
  if (since === null || since === undefined) return "–";
  const seconds = (performance.now() - since) / 1000;
  return seconds < 60 ? `${seconds.toFixed(0)} s` : `${Math.round(seconds / 60)} min`;
}

function renderTables() {
  const { el, fill } = Cblrs;
  const body = (id) => $(id).querySelector("tbody");
  const names = new Map((state.scene.planes || []).map((item) => [item.id, item.name]));
  let tracks = 0, zones = 0, lines = 0;
  fill(body("planes"), state.scene.site_planes.map((id) => {
    const row = plane(id);
    tracks += row.tracks; zones += row.zones; lines += row.lines;
    const matchers = Object.entries(row.matchers);
    const up = matchers.filter(([, online]) => online).length;
    const health = matchers.length ? `${up}/${matchers.length} online`
      : row.live ? "summarising" : "–";
    const cameras = Object.values(state.cameras).filter((camera) => camera.plane === id);
    const online = cameras.filter((camera) => camera.online).length;
    return el("tr", { dataset: { plane: String(id) } },
      el("td", {}, el("a", { href: `/?plane=${id}`, className: "plane-link" },
        String(names.get(id) || `plane ${id}`))),
      el("td", { className: "tracks" }, row.tracks), el("td", { className: "zones" }, row.zones),
      el("td", { className: "lines" }, row.lines), el("td", { className: "matcher" }, health),
      el("td", {}, cameras.length ? `${online}/${cameras.length}` : "–"),
      el("td", {}, ageText(row.liveAt)));
  }));
  const total = $("site-total");
  total.querySelector(".tracks").textContent = String(tracks);
  total.querySelector(".zones").textContent = String(zones);
  total.querySelector(".lines").textContent = String(lines);
  const linkers = Object.entries(state.linkers);
  total.querySelector(".linker").textContent = linkers.length
    ? `linker ${linkers.filter(([, online]) => online).length}/${linkers.length} online`
    : state.site ? "linker summarising" : "no linker heard";
  const site = state.site || { lines: [], zones: [] };
  fill(body("site-lines"), site.lines.map((row) => el("tr", { dataset: { line: row.line } },
    el("td", {}, row.line), el("td", {}, row.positive), el("td", {}, row.negative),
    el("td", {}, row.positive + row.negative))));
  fill(body("site-zones"), site.zones.map((row) => el("tr", { dataset: { zone: row.zone } },
    el("td", {}, row.zone), el("td", {}, row.occupancy), el("td", {}, row.entries),
    el("td", {}, row.exits))));
  const shown = [...state.tracks.values()].sort((a, b) => a.plane - b.plane || a.id - b.id)
    .slice(0, MAX_TRACK_ROWS);
  fill(body("tracks"), shown.map((track) => el("tr", { dataset: { plane: String(track.plane) } },
    el("td", {}, track.plane), el("td", { className: "track" }, track.id),
    el("td", { className: "global" }, track.global === undefined ? "–" : track.global),
    el("td", {}, track.x.toFixed(1)), el("td", {}, track.y.toFixed(1)))));
  const cameraNames = state.scene.cameras.map((camera) => camera.name);
  const planeOf = dict();
  for (const camera of state.scene.cameras) planeOf[camera.name] = camera.plane;
  for (const name of Object.keys(state.cameras)) if (!cameraNames.includes(name)) cameraNames.push(name);
  fill(body("cameras"), cameraNames.map((name) => {
    const camera = state.cameras[name] || {};
    const dot = camera.online === undefined ? "unknown" : camera.online ? "on" : "off";
    const where = camera.plane !== undefined ? camera.plane : planeOf[name];
    return el("tr", { dataset: { camera: name } }, el("td", { className: "name" }, name),
      el("td", {}, where === null || where === undefined ? "all" : where),
      el("td", {}, el("span", { className: `dot ${dot}` }),
        camera.online === undefined ? "–" : camera.online ? "online" : "offline"),
      el("td", {}, camera.rate_hz === undefined ? "–" : camera.rate_hz.toFixed(1)));
  }));
  const zone = state.scene.timezone || null;
  fill($("alerts"), state.alerts.map((alert) => el("li", {},
    el("span", { className: "time" }, Cblrs.clockText(alert.timestamp, zone)),
    el("span", {}, `P${alert.plane} ${alert.state} · ${alert.rule} · ${alert.subject}`))));
  fill($("events"), state.events.map((event) => el("li", { className: `kind-${event.kind}` },
    el("span", { className: "time" }, Cblrs.clockText(event.timestamp, zone)),
    el("span", {}, event.plane === 0 ? "site" : `P${event.plane}`),
    el("span", {}, `${String(event.kind).replace("_", " ")} · ${event.place} · #${event.track}`))));
  state.tablesDirty = false;
}

function frame() {
  if (state.dirty) { state.dirty = false; draw(); }
  if (state.tablesDirty) renderTables();
  requestAnimationFrame(frame);
}

setInterval(() => {
  const now = performance.now();
  state.updates = state.updates.filter((time) => now - time < 2000);
  const linked = [...state.tracks.values()].filter((track) => track.global !== undefined).length;
  $("stat-tracks").textContent = `${state.tracks.size} tracks`;
  $("stat-global").textContent = `${linked} linked`;
  $("stat-rate").textContent = `${(state.updates.length / 2).toFixed(1)} updates/s`;
  $("clock").textContent = Cblrs.clockText(state.time, state.scene ? state.scene.timezone : null);
  // A plane whose matcher went quiet: nobody is known to be there any more.
  for (const [id, row] of state.planes) {
    if (row.wall !== null && now - row.wall > STALE_WALL_S * 1000) {
      for (const [key, track] of state.tracks) if (track.plane === id) state.tracks.delete(key);
      row.tracks = 0;
      row.wall = null;
      state.dirty = true;
    }
  }
  state.tablesDirty = true;  // ages grow
}, 1000);

// ------------------------------------------------------------------ start
Cblrs.loadSession().then(() => Cblrs.fetchJSON("/api/site?plane=all")).then((scene) => {
  state.scene = scene;
  document.title = `cblrs · ${scene.name} · all planes`;
  $("site-name").textContent = `${scene.name} · ${scene.site_planes.length} planes`;
  const names = new Map((scene.planes || []).map((item) => [item.id, item.name]));
  Cblrs.fill($("plane-links"), scene.site_planes.map((id) => Cblrs.el("a", {
    href: `/?plane=${id}`, className: "link", title: "this plane's own page",
  }, String(names.get(id) || `plane ${id}`))));
  state.view = new Cblrs.MapView($("map"), scene);
  window.addEventListener("resize", () => { state.view.resize(); state.dirty = true; });
  if (scene.live) connect();
  else showNotice("no backbone (--broker or --backbone): the site's map only");
  requestAnimationFrame(frame);
}).catch((error) => showNotice(`cannot load the site: ${error.message}`));
