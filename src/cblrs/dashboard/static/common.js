// cblrs dashboard: what both pages share — the session (who is logged in, the CSRF token
// that every write carries), building page elements from data, the site map view (metres <->
// canvas pixels) and the drawing of the site (map image or metric grid, planes, zones, lines,
// cameras).
//
// Names come from the site file and from the broker: they reach the page as text only
// (textContent, element properties, canvas fillText), never as HTML.
"use strict";

const Cblrs = (() => {
  function idColour(id, alpha) {
    const hue = ((id * 137.508) % 360 + 360) % 360;
    return alpha === undefined ? `hsl(${hue.toFixed(1)}, 85%, 58%)`
      : `hsla(${hue.toFixed(1)}, 85%, 58%, ${alpha})`;
  }

  function niceStep(span) {
    const raw = span / 8;
    const power = Math.pow(10, Math.floor(Math.log10(raw)));
    for (const step of [1, 2, 5, 10]) if (raw <= step * power) return step * power;
    return 10 * power;
  }

  // The view of a canvas onto the ground: world metres (x right, y up) <-> CSS pixels.
  class MapView {
    constructor(canvas, scene) {
      this.canvas = canvas;
      this.scene = scene;
      this.mapImage = null;
      this.staticLayer = document.createElement("canvas");
      this.dirtyStatic = true;
      if (scene.map) {
        const image = new Image();
        image.onload = () => { this.mapImage = image; this.dirtyStatic = true; };
        image.src = "/map";
      }
      this.resize();
    }

    resize() {
      const ratio = window.devicePixelRatio || 1;
      const box = this.canvas.getBoundingClientRect();
      this.width = Math.max(1, box.width);
      this.height = Math.max(1, box.height);
      for (const target of [this.canvas, this.staticLayer]) {
        target.width = Math.round(this.width * ratio);
        target.height = Math.round(this.height * ratio);
      }
      this.ratio = ratio;
      const [x0, y0, x1, y1] = this.scene.bounds;
      const scale = Math.min(this.width / (x1 - x0), this.height / (y1 - y0));
      this.scale = scale;
      this.offsetX = (this.width - (x1 - x0) * scale) / 2 - x0 * scale;
      this.offsetY = (this.height - (y1 - y0) * scale) / 2 + y1 * scale;
      this.dirtyStatic = true;
    }

    toScreen(x, y) { return [this.offsetX + x * this.scale, this.offsetY - y * this.scale]; }
    toWorld(px, py) { return [(px - this.offsetX) / this.scale, (this.offsetY - py) / this.scale]; }

    // The site under the tracks, drawn once per resize into an offscreen canvas.
    drawStatic() {
      const ctx = this.staticLayer.getContext("2d");
      ctx.setTransform(this.ratio, 0, 0, this.ratio, 0, 0);
      ctx.fillStyle = "#0f1419";
      ctx.fillRect(0, 0, this.width, this.height);
      const scene = this.scene;
      if (this.mapImage && scene.map) {
        const m = scene.map;
        const [ax, ay] = this.toScreen(m.x_min, m.y_max);
        const [bx, by] = this.toScreen(m.x_max, m.y_min);
        ctx.globalAlpha = 0.55;
        ctx.drawImage(this.mapImage, ax, ay, bx - ax, by - ay);
        ctx.globalAlpha = 1;
      } else {
        this.drawGrid(ctx);
      }
      for (const plane of scene.planes) {
        const [ax, ay] = this.toScreen(plane.x, plane.y + plane.length);
        ctx.strokeStyle = "#3a4757";
        ctx.lineWidth = 1.5;
        ctx.strokeRect(ax, ay, plane.width * this.scale, plane.length * this.scale);
        if (scene.planes.length > 1) {  // which plane is which (names: text only)
          ctx.fillStyle = "#6f7f92";
          ctx.font = "11px system-ui";
          ctx.fillText(String(plane.name), ax + 4, ay + 13);
        }
      }
      for (const camera of scene.cameras) this.drawCamera(ctx, camera);
      this.dirtyStatic = false;
    }

    drawGrid(ctx) {
      const [x0, y0, x1, y1] = this.scene.bounds;
      const step = niceStep(Math.max(x1 - x0, y1 - y0));
      ctx.strokeStyle = "#1c242e";
      ctx.lineWidth = 1;
      ctx.fillStyle = "#4a5666";
      ctx.font = "10px system-ui";
      ctx.beginPath();
      for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) {
        const [sx] = this.toScreen(x, 0);
        ctx.moveTo(sx, 0); ctx.lineTo(sx, this.height);
      }
      for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) {
        const [, sy] = this.toScreen(0, y);
        ctx.moveTo(0, sy); ctx.lineTo(this.width, sy);
      }
      ctx.stroke();
      for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) {
        const [sx] = this.toScreen(x, 0);
        ctx.fillText(`${+x.toFixed(2)} m`, sx + 2, this.height - 4);
      }
      for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) {
        const [, sy] = this.toScreen(0, y);
        ctx.fillText(`${+y.toFixed(2)} m`, 2, sy - 2);
      }
    }

    drawCamera(ctx, camera) {
      if (camera.fov && camera.fov.length > 2) {
        ctx.beginPath();
        camera.fov.forEach(([x, y], index) => {
          const [sx, sy] = this.toScreen(x, y);
          if (index === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
        });
        ctx.closePath();
        ctx.fillStyle = "rgba(79, 179, 255, 0.05)";
        ctx.fill();
        ctx.strokeStyle = "rgba(79, 179, 255, 0.25)";
        ctx.lineWidth = 1;
        ctx.stroke();
      }
      if (camera.position) {
        const [sx, sy] = this.toScreen(camera.position[0], camera.position[1]);
        ctx.fillStyle = "#4fb3ff";
        ctx.beginPath();
        ctx.moveTo(sx, sy - 6); ctx.lineTo(sx + 5, sy + 4); ctx.lineTo(sx - 5, sy + 4);
        ctx.closePath();
        ctx.fill();
        ctx.fillStyle = "#9fcff5";
        ctx.font = "11px system-ui";
        ctx.fillText(camera.name, sx + 7, sy + 4);
      }
    }

    // Zones and lines with their labels (drawn every frame: their counts change).
    drawPlaces(ctx, labels, flashes, now) {
      for (const zone of this.scene.zones) {
        ctx.beginPath();
        zone.polygon.forEach(([x, y], index) => {
          const [sx, sy] = this.toScreen(x, y);
          if (index === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
        });
        ctx.closePath();
        const occupied = labels.zones && labels.zones[zone.name] ? labels.zones[zone.name].now : 0;
        ctx.fillStyle = occupied > 0 ? "rgba(62, 207, 142, 0.16)" : "rgba(62, 207, 142, 0.06)";
        ctx.fill();
        ctx.strokeStyle = "rgba(62, 207, 142, 0.7)";
        ctx.lineWidth = 1.5;
        ctx.stroke();
        const [cx, cy] = zone.polygon.reduce(([ax, ay], [x, y]) => [ax + x, ay + y], [0, 0])
          .map((v) => v / zone.polygon.length);
        const [sx, sy] = this.toScreen(cx, cy);
        ctx.fillStyle = "#bff2da";
        ctx.font = "12px system-ui";
        ctx.textAlign = "center";
        ctx.fillText(zone.name, sx, sy - 2);
        if (labels.zones && labels.zones[zone.name]) {
          ctx.font = "bold 12px system-ui";
          ctx.fillText(labels.zones[zone.name].text, sx, sy + 13);
        }
        ctx.textAlign = "start";
      }
      for (const line of this.scene.lines) {
        const [ax, ay] = this.toScreen(line.start[0], line.start[1]);
        const [bx, by] = this.toScreen(line.end[0], line.end[1]);
        const flashing = flashes && flashes[line.name] && now - flashes[line.name] < 800;
        ctx.strokeStyle = flashing ? "#ffffff" : "#f5b942";
        ctx.lineWidth = flashing ? 4 : 2.5;
        ctx.beginPath(); ctx.moveTo(ax, ay); ctx.lineTo(bx, by); ctx.stroke();
        // An arrow towards the positive side, at the middle of the line.
        const mx = (ax + bx) / 2, my = (ay + by) / 2;
        const nx = line.normal[0], ny = -line.normal[1];
        ctx.beginPath();
        ctx.moveTo(mx, my); ctx.lineTo(mx + nx * 16, my + ny * 16);
        ctx.moveTo(mx + nx * 16 - ny * 4 - nx * 5, my + ny * 16 + nx * 4 - ny * 5);
        ctx.lineTo(mx + nx * 16, my + ny * 16);
        ctx.lineTo(mx + nx * 16 + ny * 4 - nx * 5, my + ny * 16 - nx * 4 - ny * 5);
        ctx.stroke();
        ctx.fillStyle = "#ffe2a3";
        ctx.font = "12px system-ui";
        const text = labels.lines && labels.lines[line.name] ? labels.lines[line.name] : "";
        ctx.fillText(`${line.name} ${text}`, Math.max(ax, bx) + 6, (ay + by) / 2 - 6);
      }
    }
  }

  // ---------------------------------------------------------------- session
  let session = null;

  function toLogin() {
    location.assign(`/login?next=${encodeURIComponent(location.pathname + location.search)}`);
  }

  // Who is logged in; a page without a session goes to the login page.
  async function loadSession() {
    const response = await fetch("/api/session", { credentials: "same-origin" });
    if (response.status === 401) {
      toLogin();
      throw new Error("not logged in");
    }
    if (!response.ok) throw new Error(`cannot read the session (${response.status})`);
    session = await response.json();
    const user = document.getElementById("user");
    if (user) user.textContent = `${session.user} · ${session.role}`;
    for (const element of document.querySelectorAll("[data-admin]")) {
      element.classList.toggle("hidden", session.role !== "admin");
    }
    const logout = document.getElementById("logout");
    if (logout) logout.addEventListener("click", logoutNow);
    return session;
  }

  async function logoutNow() {
    try { await fetchJSON("/api/logout", { method: "POST", body: "{}" }); } catch (error) { /* gone */ }
    location.assign("/login");
  }

  // A stream that broke: if the session ended, go and log in again.
  async function checkSession() {
    const response = await fetch("/api/session", { credentials: "same-origin" });
    if (response.status === 401) toLogin();
  }

  // JSON requests of this site; writes carry the session's CSRF token.
  function fetchJSON(url, options) {
    const init = { ...(options || {}), credentials: "same-origin" };
    const method = (init.method || "GET").toUpperCase();
    const headers = new Headers(init.headers || {});
    if (method !== "GET" && method !== "HEAD") {
      headers.set("Content-Type", "application/json");
      if (session && session.csrf) headers.set("X-CSRF-Token", session.csrf);
    }
    init.headers = headers;
    return fetch(url, init).then(async (response) => {
      if (response.status === 401 && url !== "/api/logout") {
        toLogin();
        throw new Error("logged out");
      }
      const data = await response.json();
      if (!response.ok) throw new Error(data.error || `${response.status}`);
      return data;
    });
  }

  // ---------------------------------------------------------------- elements
  // el("td", {className: "now"}, "text", child, ...): an element; strings become text nodes.
  function el(tag, properties, ...children) {
    const element = document.createElement(tag);
    for (const [key, value] of Object.entries(properties || {})) {
      if (key === "dataset") Object.assign(element.dataset, value);
      else element[key] = value;
    }
    for (const child of children) {
      if (child === null || child === undefined) continue;
      element.append(child instanceof Node ? child : document.createTextNode(String(child)));
    }
    return element;
  }

  // Replace an element's children with these (text or elements).
  function fill(element, children) {
    element.replaceChildren(...children.map((child) =>
      child instanceof Node ? child : document.createTextNode(String(child))));
  }

  // Epoch seconds as a wall-clock time in the site's IANA zone (Intl.DateTimeFormat),
  // labelled with the zone's abbreviation or offset; UTC when the site has no zone.
  // Small numbers are scene seconds (a replay of an offline scene), not dates.
  const clockFormats = new Map();
  function clockFormat(zone, withDate) {
    const key = `${zone}|${withDate}`;
    if (!clockFormats.has(key)) {
      clockFormats.set(key, new Intl.DateTimeFormat("en-GB", {
        timeZone: zone, hourCycle: "h23", hour: "2-digit", minute: "2-digit",
        second: "2-digit", fractionalSecondDigits: 1, timeZoneName: "short",
        ...(withDate ? { year: "numeric", month: "2-digit", day: "2-digit" } : {}),
      }));
    }
    return clockFormats.get(key);
  }

  function clockText(seconds, zone, withDate = false) {
    if (seconds === null || seconds === undefined) return "–";
    if (seconds > 1e8) {
      if (!zone) {
        const iso = new Date(seconds * 1000).toISOString();
        return (withDate ? `${iso.slice(0, 10)} ` : "") + iso.slice(11, 22) + " UTC";
      }
      const parts = clockFormat(zone, withDate).formatToParts(new Date(seconds * 1000));
      const part = (type) => (parts.find((item) => item.type === type) || {}).value || "";
      const time = `${part("hour")}:${part("minute")}:${part("second")}.${part("fractionalSecond")}`;
      const date = withDate ? `${part("year")}-${part("month")}-${part("day")} ` : "";
      return `${date}${time} ${part("timeZoneName")}`;
    }
    return `t = ${seconds.toFixed(1)} s`;
  }

  // Whether the site is open at epoch seconds on its zone's wall clock, by the opening hours
  // of /api/site ({mon: "07:00-19:00", sat: "09:00-12:00, 13:00-17:00", sun: "closed"}):
  // ranges are half-open, as in the analytics. No hours: always open.
  const WEEKDAYS = ["mon", "tue", "wed", "thu", "fri", "sat", "sun"];
  function openAt(seconds, zone, hours) {
    if (!hours) return true;
    const parts = new Intl.DateTimeFormat("en-GB", {
      timeZone: zone || "UTC", weekday: "short", hourCycle: "h23", hour: "2-digit",
      minute: "2-digit", second: "2-digit",
    }).formatToParts(new Date(seconds * 1000));
    const part = (type) => parts.find((item) => item.type === type).value;
    const day = WEEKDAYS[WEEKDAYS.indexOf(part("weekday").slice(0, 3).toLowerCase())];
    const wall = Number(part("hour")) * 3600 + Number(part("minute")) * 60 + Number(part("second"));
    const text = hours[day] || "closed";
    if (text === "closed") return false;
    const clock = (time) => time.split(":").reduce((total, value) => total * 60 + Number(value), 0) * 60;
    return text.split(",").some((range) => {
      const [start, end] = range.trim().split("-").map(clock);
      return start <= wall && wall < end;
    });
  }

  // The plane a page of the overview follows (its ?plane=N), as a query for the API: "" on
  // a dashboard of one plane, "?plane=N" on a plane's page of a site's overview.
  function planeQuery(separator = "?") {
    const plane = new URLSearchParams(location.search).get("plane");
    return plane ? `${separator}plane=${encodeURIComponent(plane)}` : "";
  }

  // A track's label: its plane's id, and its global id (from the linker) beside it.
  function trackLabel(id, globalId) {
    return globalId === null || globalId === undefined ? String(id) : `${id} · G${globalId}`;
  }

  return { idColour, MapView, fetchJSON, clockText, openAt, loadSession, checkSession, el, fill,
    planeQuery, trackLabel, session: () => session };
})();
