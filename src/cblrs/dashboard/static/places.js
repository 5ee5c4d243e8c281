// cblrs dashboard: the places editor (admins) and the heatmap layer of the live map.
//
// Editor: "Edit places" turns the map into a drawing board for the shown plane's zones and
// counting lines: "Line" then two clicks draws a line; "Zone" then clicks, and a double-click
// (or Enter) closes the polygon; in "Select", a click picks a place (its name goes to the text
// box, to rename it), dragging a vertex moves it and dragging a place moves all of it; a
// double-click on an edge of the picked zone adds a vertex, a shift-click on a vertex removes
// it; Delete removes the picked place. "Save" sends the whole list to /api/places/save (the server checks
// it, writes the site file and answers one sentence when it refuses); "Cancel" drops the
// edits. Names are drawn with fillText and shown with textContent / input values only.
//
// Heatmap: every position of the live (or replayed) tracks adds to a grid of cells over the
// map, fading with a time constant of HEAT_TAU_S; drawn as a translucent image under the
// tracks when the "heatmap" box is ticked.
"use strict";

const CblrsPlaces = (() => {
  const HEAT_TAU_S = 60;
  const HEAT_CELLS = 120;       // cells along the longer side of the map
  const HEAT_SPREAD = 2;        // cells each side that a position warms
  const HEAT_KERNEL = [];       // weights of the (2 * HEAT_SPREAD + 1)^2 cells around one
  for (let dy = -HEAT_SPREAD; dy <= HEAT_SPREAD; dy += 1) {
    for (let dx = -HEAT_SPREAD; dx <= HEAT_SPREAD; dx += 1) {
      HEAT_KERNEL.push(Math.exp(-(dx * dx + dy * dy) / HEAT_SPREAD));
    }
  }
  const HANDLE_PX = 8;          // how near a vertex a press grabs it
  const LINE_PICK_PX = 7;       // how near a line a press picks it
  const $ = (id) => document.getElementById(id);

  // ---------------------------------------------------------------- heatmap
  const heat = { grid: null, cols: 0, rows: 0, x0: 0, y0: 0, cell: 1, added: 0,
    image: null, dirty: false, lastDecay: performance.now() };

  function heatReset(bounds) {
    const [x0, y0, x1, y1] = bounds;
    heat.cell = Math.max(Math.max(x1 - x0, y1 - y0) / HEAT_CELLS, 0.1);
    heat.cols = Math.max(1, Math.ceil((x1 - x0) / heat.cell));
    heat.rows = Math.max(1, Math.ceil((y1 - y0) / heat.cell));
    heat.x0 = x0; heat.y0 = y0;
    heat.grid = new Float32Array(heat.cols * heat.rows);
    heat.image = document.createElement("canvas");
    heat.image.width = heat.cols;
    heat.image.height = heat.rows;
    heat.added = 0;
    heat.dirty = true;
  }

  // rows: [[id, x, y, ...], ...] in metres.
  function heatAdd(rows) {
    if (!heat.grid) return;
    for (const row of rows) {
      const col = Math.floor((row[1] - heat.x0) / heat.cell);
      const line = Math.floor((row[2] - heat.y0) / heat.cell);
      if (col < 0 || line < 0 || col >= heat.cols || line >= heat.rows) continue;
      // A soft spot (a person covers more than one cell; positions jitter by a few).
      for (let dy = -HEAT_SPREAD; dy <= HEAT_SPREAD; dy += 1) {
        for (let dx = -HEAT_SPREAD; dx <= HEAT_SPREAD; dx += 1) {
          const c = col + dx, l = line + dy;
          if (c < 0 || l < 0 || c >= heat.cols || l >= heat.rows) continue;
          heat.grid[l * heat.cols + c] += HEAT_KERNEL[(dy + HEAT_SPREAD) * (2 * HEAT_SPREAD + 1)
            + dx + HEAT_SPREAD];
        }
      }
      heat.added += 1;
    }
    heat.dirty = true;
  }

  function heatDecay() {
    if (!heat.grid) return;
    const now = performance.now();
    const factor = Math.exp(-(now - heat.lastDecay) / 1000 / HEAT_TAU_S);
    heat.lastDecay = now;
    for (let i = 0; i < heat.grid.length; i += 1) heat.grid[i] *= factor;
    heat.dirty = true;
  }

  function heatRender() {
    let max = 0;
    for (const value of heat.grid) if (value > max) max = value;
    const ctx = heat.image.getContext("2d");
    const pixels = ctx.createImageData(heat.cols, heat.rows);
    if (max > 0) {
      for (let line = 0; line < heat.rows; line += 1) {
        for (let col = 0; col < heat.cols; col += 1) {
          const level = Math.sqrt(heat.grid[line * heat.cols + col] / max);
          if (level < 0.01) continue;
          // The image's top row is the grid's highest y (the map has y up).
          const at = ((heat.rows - 1 - line) * heat.cols + col) * 4;
          // Blue (rare) -> yellow -> red (most frequent).
          const low = Math.min(1, level * 2), high = Math.max(0, level * 2 - 1);
          pixels.data[at] = Math.round(60 + 195 * low);
          pixels.data[at + 1] = Math.round(140 + 90 * low - 200 * high);
          pixels.data[at + 2] = Math.round(255 * (1 - low));
          pixels.data[at + 3] = Math.round(40 + 190 * level);
        }
      }
    }
    ctx.putImageData(pixels, 0, 0);
    heat.dirty = false;
  }

  function heatDraw(ctx, view) {
    if (!heat.grid || !$("heatmap").checked) return;
    if (heat.dirty) heatRender();
    const [ax, ay] = view.toScreen(heat.x0, heat.y0 + heat.rows * heat.cell);
    const [bx, by] = view.toScreen(heat.x0 + heat.cols * heat.cell, heat.y0);
    ctx.imageSmoothingEnabled = true;
    ctx.drawImage(heat.image, ax, ay, bx - ax, by - ay);
  }

  // ---------------------------------------------------------------- editor
  const editor = { on: false, places: [], original: null, version: null, selected: null,
    mode: "select", drawing: null, drag: null, mouse: null, view: null, redraw: () => {},
    onSaved: () => {}, notify: () => {} };

  const copy = (value) => JSON.parse(JSON.stringify(value));
  const isLine = (place) => place.kind === "line";
  const points = (place) => (isLine(place) ? [place.start, place.end] : place.polygon);

  function message(text, bad) {
    const box = $("places-message");
    box.textContent = text;
    box.classList.toggle("error", Boolean(bad));
  }

  function freeName(stem) {
    const taken = new Set(editor.places.map((place) => place.name));
    for (let number = 1; ; number += 1) if (!taken.has(`${stem} ${number}`)) return `${stem} ${number}`;
  }

  // A moved line keeps its positive side: the normal nearest the one it had.
  function keepDirection(line) {
    if (!line.direction) return;
    const dx = line.end[0] - line.start[0], dy = line.end[1] - line.start[1];
    const length = Math.hypot(dx, dy);
    if (length < 1e-9) return;
    const left = [-dy / length, dx / length];
    const side = left[0] * line.direction[0] + left[1] * line.direction[1];
    line.direction = side < 0 ? [-left[0], -left[1]] : left;
  }

  async function open() {
    const view = await Cblrs.fetchJSON(`/api/places${Cblrs.planeQuery()}`);
    editor.places = [
      ...view.zones.map((zone) => ({ ...zone, kind: "zone" })),
      ...view.lines.map((line) => ({ ...line, kind: "line" })),
    ];
    editor.original = copy(editor.places);
    editor.version = view.version;
    editor.on = true;
    editor.selected = null;
    setMode("select");
    $("places-editor").classList.remove("hidden");
    $("edit-places").classList.add("active");
    $("map").classList.add("editing");
    message(view.other ? `${view.other} places of other planes are kept as they are.` : "");
    editor.redraw();
  }

  function close() {
    editor.on = false;
    editor.drawing = null;
    editor.drag = null;
    $("places-editor").classList.add("hidden");
    $("edit-places").classList.remove("active");
    $("map").classList.remove("editing");
    editor.redraw();
  }

  function setMode(mode) {
    editor.mode = mode;
    editor.drawing = null;
    for (const [id, name] of [["draw-select", "select"], ["draw-line", "line"], ["draw-zone", "zone"]]) {
      $(id).classList.toggle("active", mode === name);
    }
    editor.redraw();
  }

  function select(place) {
    editor.selected = place;
    $("place-name").value = place ? place.name : "";
    $("place-name").disabled = !place;
    $("delete-place").disabled = !place;
    editor.redraw();
  }

  async function save() {
    const zones = [], lines = [];
    for (const place of editor.places) {
      const { kind, ...data } = place;
      (kind === "line" ? lines : zones).push(data);
    }
    $("save-places").disabled = true;
    try {
      const result = await Cblrs.fetchJSON(`/api/places/save${Cblrs.planeQuery()}`, { method: "POST",
        body: JSON.stringify({ zones, lines, version: editor.version }) });
      close();
      await editor.onSaved();
      message("", false);
      editor.notify(`saved ${result.zones} zones and ${result.lines} lines; ${result.note}`);
    } catch (error) {
      message(`not saved: ${error.message}`, true);
    } finally {
      $("save-places").disabled = false;
    }
  }

  // ---------------------------------------------------------------- mouse
  function screenPoint(event) {
    const box = $("map").getBoundingClientRect();
    return [event.clientX - box.left, event.clientY - box.top];
  }

  function distanceToSegment([px, py], [ax, ay], [bx, by]) {
    const ex = bx - ax, ey = by - ay;
    const t = Math.max(0, Math.min(1, ((px - ax) * ex + (py - ay) * ey) / (ex * ex + ey * ey || 1)));
    return Math.hypot(px - ax - t * ex, py - ay - t * ey);
  }

  function inside([x, y], polygon) {
    let result = false;
    for (let i = 0, j = polygon.length - 1; i < polygon.length; j = i, i += 1) {
      const [ax, ay] = polygon[i], [bx, by] = polygon[j];
      if ((ay > y) !== (by > y) && x < ax + ((y - ay) * (bx - ax)) / (by - ay)) result = !result;
    }
    return result;
  }

  // What is under a screen point: a vertex (the picked place's first), else a line or a
  // zone's edge, else the inside of a zone.
  function hit(screen) {
    const view = editor.view;
    const order = editor.selected ? [editor.selected, ...editor.places] : editor.places;
    for (const place of order) {
      const list = points(place);
      for (let index = 0; index < list.length; index += 1) {
        const [sx, sy] = view.toScreen(list[index][0], list[index][1]);
        if (Math.hypot(sx - screen[0], sy - screen[1]) <= HANDLE_PX) return { place, index };
      }
    }
    for (const place of editor.places) {
      const list = points(place);
      const edges = isLine(place) ? 1 : list.length;
      for (let index = 0; index < edges; index += 1) {
        const next = list[(index + 1) % list.length];
        if (distanceToSegment(screen, view.toScreen(...list[index]), view.toScreen(...next))
          <= LINE_PICK_PX) return { place, index: null };
      }
    }
    const world = view.toWorld(...screen);
    for (const place of editor.places) {
      if (!isLine(place) && inside(world, place.polygon)) return { place, index: null };
    }
    return null;
  }

  function onDown(event) {
    if (!editor.on || event.button !== 0) return;
    const screen = screenPoint(event);
    const world = editor.view.toWorld(...screen).map((v) => Math.round(v * 1000) / 1000);
    if (editor.mode === "line") {
      if (!editor.drawing) { editor.drawing = [world]; editor.redraw(); return; }
      const line = { kind: "line", name: freeName("line"), start: editor.drawing[0], end: world };
      editor.places.push(line);
      setMode("select");
      select(line);
      return;
    }
    if (editor.mode === "zone") {
      editor.drawing ||= [];
      const last = editor.drawing[editor.drawing.length - 1];
      // The second press of a double-click lands on the vertex just added: not a new one.
      if (last) {
        const [lx, ly] = editor.view.toScreen(...last);
        if (Math.hypot(lx - screen[0], ly - screen[1]) < 4) return;
      }
      editor.drawing.push(world);
      editor.redraw();
      return;
    }
    const found = hit(screen);
    // Shift-click on a zone's vertex removes it (a zone keeps three).
    if (found && event.shiftKey && found.index !== null && !isLine(found.place)) {
      if (found.place.polygon.length > 3) found.place.polygon.splice(found.index, 1);
      select(found.place);
      return;
    }
    select(found ? found.place : null);
    if (found) editor.drag = { ...found, from: world, before: copy(points(found.place)) };
  }

  function onMove(event) {
    if (!editor.on) return;
    const screen = screenPoint(event);
    editor.mouse = editor.view.toWorld(...screen);
    const drag = editor.drag;
    if (drag) {
      const [x, y] = editor.mouse.map((v) => Math.round(v * 1000) / 1000);
      const list = points(drag.place);
      if (drag.index !== null) {
        list[drag.index][0] = x; list[drag.index][1] = y;
      } else {
        const dx = x - drag.from[0], dy = y - drag.from[1];
        drag.before.forEach(([bx, by], index) => {
          list[index][0] = Math.round((bx + dx) * 1000) / 1000;
          list[index][1] = Math.round((by + dy) * 1000) / 1000;
        });
      }
      if (isLine(drag.place)) keepDirection(drag.place);
    }
    if (drag || editor.drawing) editor.redraw();
  }

  function finishZone() {
    if (!editor.drawing || editor.drawing.length < 3) {
      message("a zone needs three or more vertices: click them, then double-click.", true);
      return;
    }
    const zone = { kind: "zone", name: freeName("zone"), polygon: editor.drawing };
    editor.places.push(zone);
    setMode("select");
    select(zone);
    message("", false);
  }

  // A double-click on an edge of the picked zone adds a vertex there.
  function addVertex(event) {
    const zone = editor.selected;
    if (!zone || isLine(zone)) return;
    const screen = screenPoint(event);
    const view = editor.view;
    let best = null, nearest = LINE_PICK_PX;
    zone.polygon.forEach((vertex, index) => {
      const next = zone.polygon[(index + 1) % zone.polygon.length];
      const gap = distanceToSegment(screen, view.toScreen(...vertex), view.toScreen(...next));
      if (gap <= nearest) { nearest = gap; best = index; }
    });
    if (best === null) return;
    const world = view.toWorld(...screen).map((v) => Math.round(v * 1000) / 1000);
    zone.polygon.splice(best + 1, 0, world);
    editor.redraw();
  }

  function onKey(event) {
    if (!editor.on) return;
    const typing = event.target === $("place-name");
    if (event.key === "Escape") { editor.drawing = null; editor.redraw(); }
    else if (event.key === "Enter" && editor.mode === "zone") finishZone();
    else if ((event.key === "Delete" || event.key === "Backspace") && !typing) removeSelected();
  }

  function removeSelected() {
    if (!editor.selected) return;
    editor.places = editor.places.filter((place) => place !== editor.selected);
    select(null);
  }

  // ---------------------------------------------------------------- drawing
  function drawEditor(ctx, view) {
    const path = (list, closed) => {
      ctx.beginPath();
      list.forEach(([x, y], index) => {
        const [sx, sy] = view.toScreen(x, y);
        if (index === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
      });
      if (closed) ctx.closePath();
    };
    ctx.font = "12px system-ui";
    for (const place of editor.places) {
      const chosen = place === editor.selected;
      path(points(place), !isLine(place));
      if (!isLine(place)) {
        ctx.fillStyle = chosen ? "rgba(79, 179, 255, 0.22)" : "rgba(62, 207, 142, 0.1)";
        ctx.fill();
      }
      ctx.strokeStyle = chosen ? "#4fb3ff" : isLine(place) ? "#f5b942" : "rgba(62, 207, 142, 0.9)";
      ctx.lineWidth = chosen ? 3 : 2;
      ctx.stroke();
      for (const [x, y] of points(place)) {
        const [sx, sy] = view.toScreen(x, y);
        ctx.fillStyle = chosen ? "#4fb3ff" : "#d8dee6";
        ctx.fillRect(sx - 3.5, sy - 3.5, 7, 7);
      }
      const list = points(place);
      const [cx, cy] = list.reduce(([ax, ay], [x, y]) => [ax + x, ay + y], [0, 0])
        .map((v) => v / list.length);
      const [sx, sy] = view.toScreen(cx, cy);
      ctx.fillStyle = "#ffffff";
      ctx.textAlign = "center";
      ctx.fillText(place.name, sx, sy - 6);
      ctx.textAlign = "start";
    }
    if (editor.drawing) {
      const list = editor.mouse ? [...editor.drawing, editor.mouse] : editor.drawing;
      path(list, false);
      ctx.strokeStyle = "#4fb3ff";
      ctx.setLineDash([6, 4]);
      ctx.lineWidth = 2;
      ctx.stroke();
      ctx.setLineDash([]);
    }
  }

  // ---------------------------------------------------------------- start
  // view(): the map view; redraw(): ask for a frame; onSaved(): reload the site; notify(text):
  // say something over the map.
  function start({ view, redraw, onSaved, notify, admin }) {
    editor.redraw = redraw;
    editor.onSaved = onSaved;
    editor.notify = notify;
    Object.defineProperty(editor, "view", { get: view });
    heatReset(view().scene.bounds);
    $("heatmap").addEventListener("change", redraw);
    setInterval(() => { heatDecay(); if ($("heatmap").checked) redraw(); }, 1000);
    window.cblrsPlaces = {
      worldToScreen: (x, y) => {
        const box = $("map").getBoundingClientRect();
        const [sx, sy] = view().toScreen(x, y);
        return [box.left + sx, box.top + sy];
      },
      editing: () => editor.on,
      places: () => copy(editor.places),
      heat: () => ({ added: heat.added, cell: heat.cell }),
      addHeat: heatAdd,
    };
    if (!admin) return;  // viewers get no editor at all
    const map = $("map");
    map.addEventListener("mousedown", onDown);
    map.addEventListener("mousemove", onMove);
    window.addEventListener("mouseup", () => { editor.drag = null; });
    map.addEventListener("dblclick", (event) => {
      if (!editor.on) return;
      if (editor.mode === "zone") finishZone();
      else if (editor.mode === "select") addVertex(event);
    });
    document.addEventListener("keydown", onKey);
    $("edit-places").addEventListener("click", () => {
      if (editor.on) return;
      open().catch((error) => editor.notify(`cannot edit places: ${error.message}`));
    });
    $("draw-select").addEventListener("click", () => setMode("select"));
    $("draw-line").addEventListener("click", () => { select(null); setMode("line"); });
    $("draw-zone").addEventListener("click", () => { select(null); setMode("zone"); });
    $("delete-place").addEventListener("click", removeSelected);
    $("place-name").addEventListener("input", () => {
      if (editor.selected) { editor.selected.name = $("place-name").value; editor.redraw(); }
    });
    $("save-places").addEventListener("click", save);
    $("cancel-places").addEventListener("click", () => {
      editor.places = copy(editor.original);
      close();
    });
    select(null);
  }

  return {
    start,
    editing: () => editor.on,
    draw: drawEditor,
    heatAdd,
    heatDraw,
    heatReset,
  };
})();
