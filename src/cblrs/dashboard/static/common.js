// cblrs dashboard: what both pages share — the session (who is logged in, the page token
// that every request carries, the event streams read with it), building page elements from data, the site map view (metres <->
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
        imageURL("/map").then((url) => { image.src = url; }, () => { /* the grid instead */ });
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
  // A browser session has two secrets: the cookie (HttpOnly; the browser sends it) and the
  // page token, which the login's answer gave and which lives here only, in this origin's
  // sessionStorage (scheme, host and port: a page of another port of this host cannot read
  // it, though the browser sends it the cookie). Every request carries the token in
  // X-CBLRS-Session; the server refuses a cookie without it. sessionStorage survives a
  // reload and the tab's own navigation; a new tab asks the dashboard's open tabs for the
  // token (a BroadcastChannel, also this origin's only), else the user logs in again.
  const TOKEN_KEY = "cblrs-session";
  const SESSION_HEADER = "X-CBLRS-Session";
  let session = null;
  let channel = null;

  function pageToken() { return sessionStorage.getItem(TOKEN_KEY); }

  function keepToken(token) {
    if (token) sessionStorage.setItem(TOKEN_KEY, token);
    else sessionStorage.removeItem(TOKEN_KEY);
  }

  // This origin's other tabs: answer their request for the token; ask them for it.
  function tabs() {
    if (channel === null && typeof BroadcastChannel === "function") {
      channel = new BroadcastChannel("cblrs-session");
      channel.addEventListener("message", (event) => {
        if (event.data && event.data.type === "ask" && pageToken()) {
          channel.postMessage({ type: "token", token: pageToken() });
        }
      });
    }
    return channel;
  }

  function tokenFromOtherTabs(waitMs = 400) {
    const open = tabs();
    if (!open) return Promise.resolve(null);
    return new Promise((resolve) => {
      const heard = (event) => {
        if (event.data && event.data.type === "token" && event.data.token) {
          open.removeEventListener("message", heard);
          clearTimeout(timer);
          resolve(event.data.token);
        }
      };
      const timer = setTimeout(() => { open.removeEventListener("message", heard); resolve(null); },
        waitMs);
      open.addEventListener("message", heard);
      open.postMessage({ type: "ask" });
    });
  }

  // Requests of this site: the page token on every one.
  function authFetch(url, init) {
    const options = { ...(init || {}), credentials: "same-origin" };
    const headers = new Headers(options.headers || {});
    const token = pageToken();
    if (token) headers.set(SESSION_HEADER, token);
    options.headers = headers;
    return fetch(url, options);
  }

  function toLogin() {
    keepToken(null);
    location.assign(`/login?next=${encodeURIComponent(location.pathname + location.search)}`);
  }

  // Who is logged in; a page without a session goes to the login page.
  async function loadSession() {
    tabs();
    if (!pageToken()) keepToken(await tokenFromOtherTabs());
    const response = await authFetch("/api/session");
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
    keepToken(null);
    location.assign("/login");
  }

  // A stream that broke: if the session ended, go and log in again.
  async function checkSession() {
    const response = await authFetch("/api/session");
    if (response.status === 401) toLogin();
  }

  // JSON requests of this site (writes as JSON).
  function fetchJSON(url, options) {
    const init = { ...(options || {}) };
    const method = (init.method || "GET").toUpperCase();
    const headers = new Headers(init.headers || {});
    if (method !== "GET" && method !== "HEAD") headers.set("Content-Type", "application/json");
    init.headers = headers;
    return authFetch(url, init).then(async (response) => {
      if (response.status === 401 && url !== "/api/logout") {
        toLogin();
        throw new Error("logged out");
      }
      const data = await response.json();
      if (!response.ok) throw new Error(data.error || `${response.status}`);
      return data;
    });
  }

  // An image of this site (the map, a camera's frame), fetched with the page token: an
  // object URL for an <img> (the policy allows blob: images).
  async function imageURL(url) {
    const response = await authFetch(url);
    if (response.status === 401) {
      toLogin();
      throw new Error("logged out");
    }
    if (!response.ok) throw new Error(`${url}: ${response.status}`);
    return URL.createObjectURL(await response.blob());
  }

  // A stream of Server-Sent Events read with fetch (an EventSource cannot send the page
  // token), behaving as an EventSource does: onopen on a 200 answer; onmessage({data}) per
  // event; onerror when the stream fails or ends, then a new try after RETRY_MS unless the
  // answer was an HTTP error or close() was called (an onerror handler may call it).
  const RETRY_MS = 3000;
  function eventStream(url, handlers) {
    const stream = { closed: false, controller: null, close() {
      this.closed = true;
      if (this.controller) this.controller.abort();
    } };
    const failed = (retry) => {
      if (stream.closed) return;
      if (handlers.onerror) handlers.onerror();
      if (retry && !stream.closed) setTimeout(open, RETRY_MS);
    };
    async function open() {
      if (stream.closed) return;
      stream.controller = new AbortController();
      let response;
      try {
        response = await authFetch(url, { signal: stream.controller.signal,
          headers: { Accept: "text/event-stream" } });
      } catch (error) {
        failed(true);
        return;
      }
      if (!response.ok || !response.body) {
        failed(false);
        return;
      }
      if (handlers.onopen) handlers.onopen();
      const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
      let buffer = "";
      try {
        for (;;) {
          const { value, done } = await reader.read();
          if (done) break;
          buffer += value.replace(/\r\n?/g, "\n");
          let end;
          while ((end = buffer.indexOf("\n\n")) >= 0) {
            const block = buffer.slice(0, end);
            buffer = buffer.slice(end + 2);
            const data = block.split("\n").filter((line) => line.startsWith("data:"))
              .map((line) => line.slice(line.startsWith("data: ") ? 6 : 5));
            if (data.length && handlers.onmessage && !stream.closed) {
              try {  // a handler's error is its own, as with an EventSource: read on
                handlers.onmessage({ data: data.join("\n") });
              } catch (error) { console.error(error); }
            }
          }
        }
      } catch (error) { /* aborted or broken: as an end */ }
      failed(true);
    }
    open();
    return stream;
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

  return { idColour, MapView, fetchJSON, imageURL, eventStream, clockText, openAt,
    loadSession, checkSession, el, fill, planeQuery, trackLabel, session: () => session };
})();
