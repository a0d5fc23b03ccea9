// The page: the station's view (/api/events: a `state` snapshot, then tile, pose, status
// and alive events), drawn on the map, and a panel per boat.
"use strict";

const COLOURS = ["#ff8c1a", "#3fc1ff", "#b4e33d", "#ff5ca8", "#c792ff", "#ffd23f"];
const MAX_TRACK = 20000; // the server's bound too; beyond it the track is thinned

const model = { epsg: null, vehicles: new Map() };
const prefs = new Map(); // "vehicle/survey" -> {visible, opacity}: kept across resyncs
const view = new MapView(document.getElementById("canvas"));
let frameWanted = false;
let panelWanted = false;

// --- the model -----------------------------------------------------------------------------

function vehicleOf(name) {
  let v = model.vehicles.get(name);
  if (!v) {
    v = { name, alive: null, status: null, pose: null, track: [], trackEpsg: null,
          surveys: new Map() };
    model.vehicles.set(name, v);
  }
  return v;
}

function surveyOf(v, id, grid) {
  let s = v.surveys.get(id);
  if (!s) {
    s = { id, epsg: grid.epsg, res_m: grid.res_m, size_px: grid.size_px, tiles: new Map() };
    v.surveys.set(id, s);
  }
  return s;
}

function pref(vehicle, survey) {
  const key = `${vehicle}/${survey}`;
  if (!prefs.has(key)) prefs.set(key, { visible: true, opacity: 1 });
  return prefs.get(key);
}

// Take a tile (col, row, version, west, north) and fetch its PNG when newer than held.
function takeTile(v, s, t) {
  const key = `${t.col}/${t.row}`;
  let tile = s.tiles.get(key);
  if (!tile) {
    tile = { col: t.col, row: t.row, west: t.west, north: t.north, version: -1,
             img: null, imgVersion: -1, drawnVersion: -1, loading: -1 };
    s.tiles.set(key, tile);
  }
  tile.version = Math.max(tile.version, t.version);
  if (tile.imgVersion >= tile.version || tile.loading >= tile.version) return;
  const version = tile.version;
  tile.loading = version;
  const img = new Image();
  const src = `/api/tile/${encodeURIComponent(v.name)}/${encodeURIComponent(s.id)}/` +
    `${t.col}/${t.row}.png?v=${version}`;
  img.src = src;
  img.decode().then(() => {
    if (version > tile.imgVersion) {
      tile.img = img;
      tile.imgVersion = version;
      requestFrame();
    }
  }).catch(() => {}).finally(() => {
    if (tile.loading === version) tile.loading = -1;
  });
}

function applyState(state) {
  model.epsg = state.epsg;
  const seen = new Set();
  for (const [name, raw] of Object.entries(state.vehicles)) {
    seen.add(name);
    const v = vehicleOf(name);
    v.alive = raw.alive;
    v.status = raw.status;
    v.pose = raw.pose;
    v.track = raw.track;
    v.trackEpsg = raw.track_epsg;
    for (const [id, rawSurvey] of Object.entries(raw.surveys)) {
      const s = surveyOf(v, id, rawSurvey);
      for (const t of rawSurvey.tiles) takeTile(v, s, t);
    }
  }
  for (const name of [...model.vehicles.keys()]) if (!seen.has(name)) model.vehicles.delete(name);
  changed();
}

function applyTile(d) {
  if (model.epsg === null) model.epsg = d.epsg;
  const v = vehicleOf(d.vehicle);
  takeTile(v, surveyOf(v, d.survey, d), d);
  changed();
}

function applyPose(d) {
  const v = vehicleOf(d.vehicle);
  if (model.epsg === null) model.epsg = d.epsg;
  if (d.epsg !== v.trackEpsg) {
    v.track = [];
    v.trackEpsg = d.epsg;
  }
  v.track.push([d.east, d.north]);
  if (v.track.length > MAX_TRACK) {
    const last = v.track[v.track.length - 1];
    v.track = v.track.filter((_, i) => i % 2 === 0);
    v.track.push(last);
  }
  v.pose = d;
  changed();
}

// --- drawing -------------------------------------------------------------------------------

function requestFrame() {
  if (frameWanted) return;
  frameWanted = true;
  requestAnimationFrame(draw);
}

function colourOf(name) {
  const names = [...model.vehicles.keys()].sort();
  return COLOURS[Math.max(names.indexOf(name), 0) % COLOURS.length];
}

function draw() {
  frameWanted = false;
  view.begin();
  for (const v of model.vehicles.values()) {
    const live = liveSurvey(v);
    const order = [...v.surveys.values()].sort((a, b) => (a.id === live) - (b.id === live));
    for (const s of order) {
      const p = pref(v.name, s.id);
      if (!p.visible || s.epsg !== model.epsg) continue;
      const side = s.res_m * s.size_px;
      for (const tile of s.tiles.values()) {
        if (tile.img && view.drawTile(tile.img, tile.west, tile.north, side, p.opacity)) {
          tile.drawnVersion = tile.imgVersion;
        }
      }
    }
  }
  for (const v of model.vehicles.values()) {
    if (v.trackEpsg === model.epsg) view.drawTrack(v.track, colourOf(v.name));
  }
  for (const v of model.vehicles.values()) {
    const p = v.pose;
    if (!p || p.epsg !== model.epsg) continue;
    const zone = seamapUtm.zoneOf(p.epsg);
    const gamma = zone ? seamapUtm.toLatLon(p.east, p.north, zone.zone, zone.south)
      .convergenceDeg : 0;
    // The heading is from true north; the screen's up is grid north.
    view.drawBoat(p.east, p.north, p.heading_deg - gamma, colourOf(v.name), v.name,
                  v.alive === false);
  }
  drawScale();
}

function drawScale() {
  const bar = view.scaleBar(120);
  document.getElementById("scale-bar").style.width = `${bar.px}px`;
  const m = bar.metres;
  document.getElementById("scale-label").textContent =
    m >= 1000 ? `${m / 1000} km` : m >= 1 ? `${m} m` : `${Math.round(m * 100)} cm`;
}

// Fit the view to every tile and track, until the user pans or zooms.
function fitAll() {
  let w = Infinity, s = Infinity, e = -Infinity, n = -Infinity;
  for (const v of model.vehicles.values()) {
    for (const sv of v.surveys.values()) {
      if (sv.epsg !== model.epsg) continue;
      const side = sv.res_m * sv.size_px;
      for (const t of sv.tiles.values()) {
        w = Math.min(w, t.west); e = Math.max(e, t.west + side);
        n = Math.max(n, t.north); s = Math.min(s, t.north - side);
      }
    }
    if (v.trackEpsg === model.epsg) {
      for (const [pe, pn] of v.track) {
        w = Math.min(w, pe); e = Math.max(e, pe); s = Math.min(s, pn); n = Math.max(n, pn);
      }
    }
  }
  if (w <= e && s <= n) view.fit(w - 5, s - 5, e + 5, n + 5);
}

function changed() {
  if (!pointerOn) showPointer(null, null); // the zone may just have become known
  if (!view.touched) fitAll();
  requestFrame();
  schedulePanel();
}

// --- the pointer's coordinates -------------------------------------------------------------

let pointerOn = false;

function showPointer(x, y) {
  pointerOn = x !== null;
  const out = document.getElementById("readout");
  const zone = model.epsg !== null ? seamapUtm.zoneOf(model.epsg) : null;
  if (x === null || !zone) {
    out.textContent = zone ? `UTM ${zone.zone}${zone.south ? "S" : "N"}` : "no data yet";
    return;
  }
  const u = view.screenToUtm(x, y);
  const g = seamapUtm.toLatLon(u.e, u.n, zone.zone, zone.south);
  const lat = `${Math.abs(g.lat).toFixed(7)}°${g.lat < 0 ? "S" : "N"}`;
  const lon = `${Math.abs(g.lon).toFixed(7)}°${g.lon < 0 ? "W" : "E"}`;
  out.dataset.e = u.e;
  out.dataset.n = u.n;
  out.textContent = `${lat} ${lon} · E ${u.e.toFixed(2)} N ${u.n.toFixed(2)} ` +
    `UTM ${zone.zone}${zone.south ? "S" : "N"}`;
}

// --- the panel -----------------------------------------------------------------------------

function schedulePanel() {
  if (panelWanted) return;
  panelWanted = true;
  setTimeout(() => { panelWanted = false; renderPanel(); }, 250);
}

function liveSurvey(v) {
  const s = v.status && typeof v.status.survey === "string" ? v.status.survey : null;
  return v.alive !== false ? s : null;
}

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, val] of Object.entries(attrs)) {
    if (k === "class") node.className = val;
    else node.setAttribute(k, val);
  }
  for (const c of children) node.append(c);
  return node;
}

function statusRows(v) {
  const st = v.status || {};
  const num = (x, d) => (typeof x === "number" ? x.toFixed(d) : "–");
  const rows = [];
  const links = st.links && typeof st.links === "object" ? Object.entries(st.links) : [];
  rows.push(["links", links.length ? links.map(([k, l]) =>
    `${k} ${l && l.up ? "up" : "down"}`).join(", ") : "–"]);
  const f = st.frames && typeof st.frames === "object" ? st.frames : {};
  rows.push(["frames", `${f.mapped ?? "–"} mapped / ${f.rejected ?? "–"} rejected / ` +
    `${f.skipped ?? "–"} skipped`]);
  rows.push(["lag", typeof st.lag_s === "number" ? `${num(st.lag_s, 1)} s` : "–"]);
  rows.push(["disk free", typeof st.disk_free_mb === "number"
    ? `${num(st.disk_free_mb / 1024, 1)} GB` : "–"]);
  rows.push(["survey", typeof st.survey === "string" && st.survey ? st.survey : "none"]);
  const m = st.mission;
  rows.push(["mission", m && typeof m === "object"
    ? `${m.current ?? "?"} / ${m.total ?? "?"}${m.state ? ` (${m.state})` : ""}` : "–"]);
  const p = v.pose;
  rows.push(["pose", p ? `${p.lat.toFixed(6)}, ${p.lon.toFixed(6)}, ` +
    `heading ${p.heading_deg.toFixed(0)}°` : "–"]);
  return rows;
}

// The panel is rebuilt when its shape changes (boats, surveys, away or live); otherwise
// only its texts change, so a click or a slider in it is never cut short.
let panelShape = "";

function shapeOf() {
  return JSON.stringify([...model.vehicles.values()].map((v) =>
    [v.name, v.alive, liveSurvey(v), [...v.surveys.keys()]]));
}

function updatePanelTexts() {
  for (const v of model.vehicles.values()) {
    const section = document.querySelector(`section[data-vehicle="${CSS.escape(v.name)}"]`);
    if (!section) continue;
    const dds = section.querySelectorAll("dl.status dd");
    statusRows(v).forEach(([, val], i) => { if (dds[i]) dds[i].textContent = val; });
    for (const s of v.surveys.values()) {
      const li = section.querySelector(`li[data-survey="${CSS.escape(s.id)}"] .tiles`);
      if (li) li.textContent = ` ${s.tiles.size} tiles`;
    }
  }
}

function renderPanel() {
  const root = document.getElementById("vehicles");
  if (!model.vehicles.size) {
    root.replaceChildren(el("p", { class: "empty" }, "Waiting for boats…"));
    panelShape = "";
    return;
  }
  const shape = shapeOf();
  if (shape === panelShape) {
    updatePanelTexts();
    return;
  }
  panelShape = shape;
  const sections = [];
  for (const v of [...model.vehicles.values()].sort((a, b) => a.name.localeCompare(b.name))) {
    const away = v.alive === false;
    const section = el("section", { class: `vehicle${away ? " away" : ""}`,
                                    "data-vehicle": v.name });
    const badge = el("span", { class: "badge" }, away ? "away" : v.alive ? "live" : "?");
    const swatch = el("span", { class: "swatch" });
    swatch.style.background = colourOf(v.name);
    section.append(el("h2", {}, swatch, v.name, " ", badge));
    const dl = el("dl", { class: "status" });
    for (const [k, val] of statusRows(v)) dl.append(el("dt", {}, k), el("dd", {}, val));
    section.append(dl);
    const track = el("a", { href: `/files/${encodeURIComponent(v.name)}/track.geojson`,
                            download: "" }, "track.geojson");
    section.append(el("div", { class: "downloads" }, "Download: ", track));
    const list = el("ul", { class: "surveys" });
    const live = liveSurvey(v);
    for (const s of [...v.surveys.values()].sort((a, b) => a.id.localeCompare(b.id))) {
      list.append(surveyRow(v, s, s.id === live));
    }
    section.append(el("h3", {}, "Surveys"), list);
    sections.push(section);
  }
  root.replaceChildren(...sections);
}

function surveyRow(v, s, live) {
  const p = pref(v.name, s.id);
  const show = el("input", { type: "checkbox", "aria-label": `show ${s.id}` });
  show.checked = p.visible;
  show.addEventListener("change", () => { p.visible = show.checked; requestFrame(); });
  const opacity = el("input", { type: "range", min: "0", max: "100", title: "opacity",
                                "aria-label": `opacity of ${s.id}` });
  opacity.value = String(Math.round(p.opacity * 100));
  opacity.addEventListener("input", () => { p.opacity = opacity.value / 100; requestFrame(); });
  const tif = el("a", { href: `/files/${encodeURIComponent(v.name)}/` +
    `${encodeURIComponent(s.id)}/mosaic.tif`, download: "" }, "mosaic.tif");
  return el("li", { "data-survey": s.id },
    el("label", {}, show, ` ${s.id}`, live ? el("span", { class: "live" }, " live") : ""),
    el("span", { class: "tiles" }, ` ${s.tiles.size} tiles`), opacity, tif);
}

// --- wiring --------------------------------------------------------------------------------

view.onChange = requestFrame;
view.onPointer = showPointer;
document.getElementById("fit").addEventListener("click", () => {
  view.touched = false;
  fitAll();
});
const toggle = document.getElementById("panel-toggle");
toggle.addEventListener("click", () => {
  const open = document.body.classList.toggle("panel-closed") === false;
  toggle.setAttribute("aria-expanded", String(open));
});
if (window.matchMedia("(max-width: 700px)").matches) document.body.classList.add("panel-closed");

function connect() {
  const conn = document.getElementById("conn");
  const events = new EventSource("/api/events");
  const on = (kind, apply) => events.addEventListener(kind, (ev) => {
    try {
      apply(JSON.parse(ev.data));
    } catch (err) {
      console.error(kind, err);
    }
  });
  on("state", applyState);
  on("tile", applyTile);
  on("pose", applyPose);
  on("status", (d) => { vehicleOf(d.vehicle).status = d.status; changed(); });
  on("alive", (d) => { vehicleOf(d.vehicle).alive = d.alive; changed(); });
  events.onopen = () => { conn.textContent = ""; conn.className = ""; };
  // EventSource reconnects by itself; the new stream starts with a fresh state.
  events.onerror = () => { conn.textContent = "shore station unreachable, retrying…";
                           conn.className = "down"; };
}

connect();
showPointer(null, null);
requestFrame();

// For tests and the curious: the model, the view and what was last drawn.
window.seamap = {
  model,
  view,
  utm: seamapUtm,
  drawnVersion(vehicle, survey, col, row) {
    const s = model.vehicles.get(vehicle)?.surveys.get(survey);
    const t = s?.tiles.get(`${col}/${row}`);
    return t ? t.drawnVersion : -1;
  },
};
