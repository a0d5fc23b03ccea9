// The page: the station's view (/api/events: a `state` snapshot, then tile, pose, status,
// alive and coverage events), drawn on the map, and a panel per boat.
"use strict";

const COLOURS = ["#ff8c1a", "#3fc1ff", "#b4e33d", "#ff5ca8", "#c792ff", "#ffd23f"];
const MAX_TRACK = 20000; // the server's bound too; beyond it the track is thinned
const COVERAGE_OPACITY = 0.55; // the raster over the mosaic: both stay readable
const GAP_FILL = "rgba(255, 59, 48, 0.2)";
const GAP_STROKE = "#ff3b30";
const GAP_DASH = [6, 4];
const MAX_LEVEL = 10; // the server's overview pyramid: levels 1..10 over the tiles
const MAX_IMAGES = 256; // tile images held (256 x 256 RGBA: 64 MB at most)
const MAX_LOADING = 8; // image requests in flight

const model = { epsg: null, vehicles: new Map() };
const prefs = new Map(); // "vehicle/survey" -> {visible, opacity}: kept across resyncs
const view = new MapView(document.getElementById("canvas"));
let frameWanted = false;
let panelWanted = false;
let showCoverage = true;

// --- the model -----------------------------------------------------------------------------

function vehicleOf(name) {
  let v = model.vehicles.get(name);
  if (!v) {
    v = { name, alive: null, status: null, pose: null, track: [], trackIndex: new Map(),
          trackEpsg: null, surveys: new Map(), coverage: new Map() };
    model.vehicles.set(name, v);
  }
  return v;
}

function surveyOf(v, id, grid) {
  let s = v.surveys.get(id);
  if (!s) {
    s = { id, epsg: grid.epsg, res_m: grid.res_m, size_px: grid.size_px, tiles: new Map(),
          stamps: Array.from({ length: MAX_LEVEL + 1 }, () => new Map()) };
    v.surveys.set(id, s);
  }
  return s;
}

function pref(vehicle, survey) {
  const key = `${vehicle}/${survey}`;
  if (!prefs.has(key)) prefs.set(key, { visible: true, opacity: 1 });
  return prefs.get(key);
}

// Take a tile's description (col, row, version, west, north): the model holds every
// tile's, the page fetches images only for what it draws (`drawSurvey`).
function takeTile(v, s, t) {
  const key = `${t.col}/${t.row}`;
  let tile = s.tiles.get(key);
  if (!tile) {
    tile = { col: t.col, row: t.row, west: t.west, north: t.north, version: -1,
             drawnVersion: -1 };
    s.tiles.set(key, tile);
  }
  if (t.version <= tile.version) return;
  // Each overview tile's stamp is the sum of (version + 1) of the tiles under it: the
  // server's, so the URL names the image this state asks for.
  const step = t.version - tile.version;
  tile.version = t.version;
  for (let level = 1; level <= MAX_LEVEL; level++) {
    const k = `${Math.floor(t.col / 2 ** level)}/${Math.floor(t.row / 2 ** level)}`;
    const stamps = s.stamps[level];
    stamps.set(k, (stamps.get(k) || 0) + step);
  }
}

function coverageOf(v, id) {
  let c = v.coverage.get(id);
  if (!c) {
    c = { id, summary: null, raster: null, img: null, imgRaster: null, imgVersion: -1,
          loading: -1, drawnVersion: -1, gaps: [], gapsKey: "", gapsDrawn: -1 };
    v.coverage.set(id, c);
  }
  return c;
}

// Take a survey's coverage ({summary, raster}, either null until it came): each replaces
// the one held only when its version is newer; a newer raster's PNG is fetched.
function takeCoverage(v, id, d) {
  const c = coverageOf(v, id);
  if (d.summary && (!c.summary || d.summary.version > c.summary.version)) {
    c.summary = d.summary;
    c.gapsKey = ""; // projected again when next drawn
  }
  if (d.raster && (!c.raster || d.raster.version > c.raster.version)) c.raster = d.raster;
  const raster = c.raster;
  if (!raster || c.imgVersion >= raster.version || c.loading >= raster.version) return;
  const version = raster.version;
  c.loading = version;
  const img = new Image();
  img.src = `/api/coverage/${encodeURIComponent(v.name)}/${encodeURIComponent(id)}.png` +
    `?v=${version}`;
  img.decode().then(() => {
    if (version > c.imgVersion) {
      c.img = img;
      c.imgRaster = raster; // where this image lies, whatever comes after it
      c.imgVersion = version;
      requestFrame();
    }
  }).catch(() => {}).finally(() => {
    if (c.loading === version) c.loading = -1;
  });
}

// The polygons (each a list of rings of [lon, lat]) of a GeoJSON FeatureCollection's
// Polygon and MultiPolygon features; anything malformed is left out.
function polygonsOf(collection) {
  const isRing = (ring) => Array.isArray(ring) && ring.length >= 3 && ring.every((pt) =>
    Array.isArray(pt) && Number.isFinite(pt[0]) && Number.isFinite(pt[1]));
  const out = [];
  const features = collection && Array.isArray(collection.features) ? collection.features : [];
  for (const f of features) {
    const g = f && f.geometry;
    const polygons = !g ? [] : g.type === "Polygon" ? [g.coordinates]
      : g.type === "MultiPolygon" ? g.coordinates : [];
    for (const rings of Array.isArray(polygons) ? polygons : []) {
      if (Array.isArray(rings) && rings.length && rings.every(isRing)) out.push(rings);
    }
  }
  return out;
}

// A survey's gaps as rings of [east, north] in the page's UTM zone (cached per summary).
function gapsOf(c) {
  const zone = model.epsg !== null ? seamapUtm.zoneOf(model.epsg) : null;
  if (!zone || !c.summary) return [];
  const key = `${c.summary.version}/${model.epsg}`;
  if (c.gapsKey !== key) {
    c.gaps = polygonsOf(c.summary.gaps).map((rings) => rings.map((ring) => ring.map(
      ([lon, lat]) => {
        const p = seamapUtm.fromLatLon(lat, lon, zone.zone, zone.south);
        return [p.e, p.n];
      })));
    c.gapsKey = key;
  }
  return c.gaps;
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
    indexTrack(v);
    v.trackEpsg = raw.track_epsg;
    for (const [id, rawSurvey] of Object.entries(raw.surveys)) {
      const s = surveyOf(v, id, rawSurvey);
      for (const t of rawSurvey.tiles) takeTile(v, s, t);
    }
    for (const [id, rawCoverage] of Object.entries(raw.coverage || {})) {
      takeCoverage(v, id, rawCoverage);
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

// The track: [east, north, time] a frame, in the order the frames came, each at its
// latest pose: the boat sends the newest pose and, with it, the frames its live map has
// placed anew since (`refined`), which move their points (by time) to where the map is.
function placeOnTrack(v, e, n, time, append) {
  const at = v.trackIndex.get(time);
  if (at !== undefined) v.track[at] = [e, n, time];
  else if (append) {
    v.trackIndex.set(time, v.track.length);
    v.track.push([e, n, time]);
  }
}

function indexTrack(v) {
  v.trackIndex = new Map(v.track.map((p, k) => [p[2], k]));
}

function applyPose(d) {
  const v = vehicleOf(d.vehicle);
  if (model.epsg === null) model.epsg = d.epsg;
  if (d.epsg !== v.trackEpsg) {
    v.track = [];
    v.trackIndex = new Map();
    v.trackEpsg = d.epsg;
  }
  placeOnTrack(v, d.east, d.north, d.time, true);
  for (const [e, n, time] of d.refined || []) placeOnTrack(v, e, n, time, false);
  if (v.track.length > MAX_TRACK) {
    const last = v.track[v.track.length - 1];
    v.track = v.track.filter((_, i) => i % 2 === 0);
    v.track.push(last);
    indexTrack(v);
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
  frame += 1;
  viewStatus.wanted = 0;
  viewStatus.drawn = 0;
  view.begin();
  for (const v of model.vehicles.values()) {
    const live = liveSurvey(v);
    const order = [...v.surveys.values()].sort((a, b) => (a.id === live) - (b.id === live));
    for (const s of order) {
      const p = pref(v.name, s.id);
      if (!p.visible || s.epsg !== model.epsg) continue;
      drawSurvey(v, s, p.opacity);
    }
  }
  evictImages();
  if (showCoverage) drawCoverage();
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

// --- the tiles drawn: at the level whose pixel matches the screen's, only those in view ---

const images = new Map(); // "vehicle/survey/level/col/row" -> {bitmap, version, loading, used}
let loadingCount = 0;
let frame = 0;
const viewStatus = { wanted: 0, drawn: 0, level: 0 }; // of the last frame, for tests

// The coarsest level whose pixel is no larger than a screen pixel (so nothing is drawn
// coarser than the screen shows it).
function levelFor(s) {
  const screenPixelM = 1 / (view.scale * view.dpr);
  const level = Math.floor(Math.log2(screenPixelM / s.res_m) + 1e-9);
  return Math.min(Math.max(level, 0), MAX_LEVEL);
}

// The tiles of a level (key -> version or stamp) that lie in view.
function tilesInView(s, level) {
  const side = s.res_m * s.size_px * 2 ** level;
  const nw = view.screenToUtm(0, 0), se = view.screenToUtm(view.width, view.height);
  const c0 = Math.floor(nw.e / side), c1 = Math.floor(se.e / side);
  const r0 = Math.floor(se.n / side), r1 = Math.floor(nw.n / side);
  const held = level === 0 ? null : s.stamps[level];
  const want = (k) => (level === 0 ? s.tiles.get(k)?.version : held.get(k));
  const size = level === 0 ? s.tiles.size : held.size;
  const out = [];
  if ((c1 - c0 + 1) * (r1 - r0 + 1) <= size) {
    for (let c = c0; c <= c1; c++) {
      for (let r = r0; r <= r1; r++) {
        const version = want(`${c}/${r}`);
        if (version !== undefined) out.push({ col: c, row: r, version });
      }
    }
  } else {
    for (const k of (level === 0 ? s.tiles.keys() : held.keys())) {
      const [c, r] = k.split("/").map(Number);
      if (c >= c0 && c <= c1 && r >= r0 && r <= r1) out.push({ col: c, row: r, version: want(k) });
    }
  }
  return { side, tiles: out };
}

function imageUrl(v, s, level, col, row, version) {
  const base = `/api/tile/${encodeURIComponent(v.name)}/${encodeURIComponent(s.id)}`;
  return level === 0 ? `${base}/${col}/${row}.png?v=${version}`
    : `${base}/${level}/${col}/${row}.png?v=${version}`;
}

// The image held for a tile (any version), and its fetch when older than `version`.
function imageOf(v, s, level, col, row, version) {
  const key = `${v.name}/${s.id}/${level}/${col}/${row}`;
  let entry = images.get(key);
  if (!entry) {
    entry = { bitmap: null, version: -1, loading: -1, used: frame, drawn: -1 };
    images.set(key, entry);
  }
  entry.used = frame;
  if (entry.version < version && entry.loading < version && loadingCount < MAX_LOADING) {
    entry.loading = version;
    loadingCount += 1;
    fetch(imageUrl(v, s, level, col, row, version))
      .then((r) => (r.ok ? r.blob() : Promise.reject(new Error(r.status))))
      .then((blob) => createImageBitmap(blob))
      .then((bitmap) => {
        if (version > entry.version && images.get(key) === entry) {
          if (entry.bitmap) entry.bitmap.close();
          entry.bitmap = bitmap;
          entry.version = version;
        } else {
          bitmap.close();
        }
      })
      .catch(() => {})
      .finally(() => {
        loadingCount -= 1;
        if (entry.loading === version) entry.loading = -1;
        requestFrame();
      });
  }
  return entry;
}

// A survey's tiles in view at the level that fits the zoom; where one's image is not in
// yet, the nearest coarser one held stands in for it (drawn first, under the others).
function drawSurvey(v, s, opacity) {
  const level = levelFor(s);
  const { side, tiles } = tilesInView(s, level);
  viewStatus.level = level;
  const standIns = new Map();
  const ready = [];
  for (const t of tiles) {
    const entry = imageOf(v, s, level, t.col, t.row, t.version);
    viewStatus.wanted += 1;
    if (entry.bitmap) ready.push([t, entry]);
    if (entry.bitmap && entry.version >= t.version) viewStatus.drawn += 1;
    if (entry.bitmap) continue;
    for (let up = level + 1; up <= MAX_LEVEL; up++) {
      const key = `${v.name}/${s.id}/${up}/${Math.floor(t.col / 2 ** (up - level))}/` +
        `${Math.floor(t.row / 2 ** (up - level))}`;
      const held = images.get(key);
      if (held && held.bitmap) {
        held.used = frame;
        standIns.set(key, [up, held, key]);
        break;
      }
    }
  }
  for (const [up, held, key] of [...standIns.values()].sort((a, b) => b[0] - a[0])) {
    const [col, row] = key.split("/").slice(-2).map(Number);
    const upSide = s.res_m * s.size_px * 2 ** up;
    view.drawTile(held.bitmap, col * upSide, (row + 1) * upSide, upSide, opacity);
  }
  for (const [t, entry] of ready) {
    view.drawTile(entry.bitmap, t.col * side, (t.row + 1) * side, side, opacity);
    if (entry.drawn !== entry.version) markDrawn(s, level, t, entry);
  }
}

// The tiles (level 0) an image drawn shows at their versions: for `drawnVersion`.
function markDrawn(s, level, t, entry) {
  entry.drawn = entry.version;
  if (entry.version !== t.version) return; // newer tiles came since: its newer image will
  if (level === 0) {
    const tile = s.tiles.get(`${t.col}/${t.row}`);
    if (tile) tile.drawnVersion = Math.max(tile.drawnVersion, tile.version);
    return;
  }
  const n = 2 ** level;
  for (const tile of s.tiles.values()) {
    if (Math.floor(tile.col / n) === t.col && Math.floor(tile.row / n) === t.row) {
      tile.drawnVersion = Math.max(tile.drawnVersion, tile.version);
    }
  }
}

// Beyond MAX_IMAGES, the images least recently drawn go (their memory freed now).
function evictImages() {
  if (images.size <= MAX_IMAGES) return;
  const old = [...images.entries()].filter(([, e]) => e.used < frame && e.loading < 0)
    .sort((a, b) => a[1].used - b[1].used);
  for (const [key, entry] of old.slice(0, images.size - MAX_IMAGES)) {
    if (entry.bitmap) entry.bitmap.close();
    images.delete(key);
  }
}

// Each shown survey's coverage raster over the mosaics, then every gap over the rasters.
function drawCoverage() {
  const shown = [];
  for (const v of model.vehicles.values()) {
    for (const c of v.coverage.values()) if (pref(v.name, c.id).visible) shown.push(c);
  }
  for (const c of shown) {
    const r = c.imgRaster;
    if (c.img && r.epsg === model.epsg && view.drawImage(
      c.img, r.west, r.north, r.cols * r.cell_m, r.rows * r.cell_m, COVERAGE_OPACITY)) {
      c.drawnVersion = c.imgVersion;
    }
  }
  for (const c of shown) {
    if (!c.summary || model.epsg === null) continue;
    const gaps = gapsOf(c);
    if (gaps.length) view.drawPolygons(gaps, GAP_FILL, GAP_STROKE, GAP_DASH);
    c.gapsDrawn = c.summary.version;
  }
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
    for (const c of v.coverage.values()) {
      const r = c.raster;
      if (!r || r.epsg !== model.epsg) continue;
      w = Math.min(w, r.west); e = Math.max(e, r.west + r.cols * r.cell_m);
      n = Math.max(n, r.north); s = Math.min(s, r.north - r.rows * r.cell_m);
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

// A survey's coverage in one line: "covered 63.4 % of 1,200 m² · 2 gaps (420 m²)", or
// "seen 812 m²" when its area is not known; "· final" once the survey-end pass made it.
function coverageText(c) {
  const s = c && c.summary;
  if (!s) return "";
  const m2 = (x) => `${Math.round(x).toLocaleString("en-US")} m²`;
  const a = s.area;
  let text;
  if (a && typeof a.fraction === "number" && typeof a.area_m2 === "number") {
    text = `covered ${(100 * a.fraction).toFixed(1)} % of ${m2(a.area_m2)}`;
    if (typeof a.gaps === "number") {
      const size = typeof a.gaps_m2 === "number" && a.gaps ? ` (${m2(a.gaps_m2)})` : "";
      text += a.gaps ? ` · ${a.gaps} gap${a.gaps === 1 ? "" : "s"}${size}` : " · no gaps";
    }
  } else if (typeof s.seen_m2 === "number") {
    text = `seen ${m2(s.seen_m2)}`;
  } else {
    return "";
  }
  return s.final === true ? `${text} · final` : text;
}

// The surveys of a boat the panel lists: those with tiles or coverage.
function surveyIds(v) {
  return [...new Set([...v.surveys.keys(), ...v.coverage.keys()])]
    .sort((a, b) => a.localeCompare(b));
}

// The panel is rebuilt when its shape changes (boats, surveys, away or live); otherwise
// only its texts change, so a click or a slider in it is never cut short.
let panelShape = "";

function shapeOf() {
  return JSON.stringify([...model.vehicles.values()].map((v) =>
    [v.name, v.alive, liveSurvey(v), surveyIds(v)]));
}

function updatePanelTexts() {
  for (const v of model.vehicles.values()) {
    const section = document.querySelector(`section[data-vehicle="${CSS.escape(v.name)}"]`);
    if (!section) continue;
    const dds = section.querySelectorAll("dl.status dd");
    statusRows(v).forEach(([, val], i) => { if (dds[i]) dds[i].textContent = val; });
    for (const id of surveyIds(v)) {
      const li = section.querySelector(`li[data-survey="${CSS.escape(id)}"]`);
      if (!li) continue;
      li.querySelector(".tiles").textContent = ` ${v.surveys.get(id)?.tiles.size ?? 0} tiles`;
      li.querySelector(".coverage").textContent = coverageText(v.coverage.get(id));
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
    for (const id of surveyIds(v)) list.append(surveyRow(v, id, id === live));
    section.append(el("h3", {}, "Surveys"), list);
    sections.push(section);
  }
  root.replaceChildren(...sections);
}

function surveyRow(v, id, live) {
  const p = pref(v.name, id);
  const show = el("input", { type: "checkbox", "aria-label": `show ${id}` });
  show.checked = p.visible;
  show.addEventListener("change", () => { p.visible = show.checked; requestFrame(); });
  const opacity = el("input", { type: "range", min: "0", max: "100", title: "opacity",
                                "aria-label": `opacity of ${id}` });
  opacity.value = String(Math.round(p.opacity * 100));
  opacity.addEventListener("input", () => { p.opacity = opacity.value / 100; requestFrame(); });
  const tif = el("a", { href: `/files/${encodeURIComponent(v.name)}/` +
    `${encodeURIComponent(id)}/mosaic.tif`, download: "" }, "mosaic.tif");
  const tiles = v.surveys.get(id)?.tiles.size ?? 0;
  return el("li", { "data-survey": id },
    el("label", {}, show, ` ${id}`, live ? el("span", { class: "live" }, " live") : ""),
    el("span", { class: "tiles" }, ` ${tiles} tiles`), opacity, tif,
    el("span", { class: "coverage" }, coverageText(v.coverage.get(id))));
}

// --- wiring --------------------------------------------------------------------------------

view.onChange = requestFrame;
view.onPointer = showPointer;
document.getElementById("fit").addEventListener("click", () => {
  view.touched = false;
  fitAll();
});
const coverageToggle = document.getElementById("show-coverage");
coverageToggle.addEventListener("change", () => {
  showCoverage = coverageToggle.checked;
  requestFrame();
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
  on("coverage", (d) => {
    if (model.epsg === null && d.raster) model.epsg = d.raster.epsg;
    takeCoverage(vehicleOf(d.vehicle), d.survey, d);
    changed();
  });
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
  // The last frame's tiles in view (wanted), those drawn at their newest version, and
  // the pyramid level drawn; the tile images held.
  viewStatus() {
    return { ...viewStatus, images: images.size, loading: loadingCount };
  },
  // The versions of a survey's coverage raster and gaps last drawn (-1: never).
  coverageDrawn(vehicle, survey) {
    const c = model.vehicles.get(vehicle)?.coverage.get(survey);
    return { raster: c ? c.drawnVersion : -1, gaps: c ? c.gapsDrawn : -1 };
  },
};
