// The map: a canvas drawn directly in the tiles' UTM zone, north up. The screen and UTM
// are tied by one affine: x = (E - centerE) * scale + width / 2, y = (centerN - N) * scale
// + height / 2 (CSS pixels; `scale` in CSS pixels per metre). Mosaic tiles are drawn
// pixel for pixel on that grid (no smoothing when zoomed in), so the pixel under the
// pointer is the GeoTIFF's pixel at the coordinates shown.
"use strict";

class MapView {
  constructor(canvas) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.centerE = 500000;
    this.centerN = 0;
    this.scale = 1; // CSS pixels per metre
    this.width = 1;
    this.height = 1;
    this.dpr = 1;
    this.touched = false; // the user has panned or zoomed: stop fitting to the data
    this.onChange = () => {};
    this.onPointer = () => {};
    this._pointers = new Map();
    this._gesture = null;
    this._resize();
    new ResizeObserver(() => this._resize()).observe(canvas);
    this._listen();
  }

  // --- the affine --------------------------------------------------------------------------

  utmToScreen(e, n) {
    return {
      x: (e - this.centerE) * this.scale + this.width / 2,
      y: (this.centerN - n) * this.scale + this.height / 2,
    };
  }

  screenToUtm(x, y) {
    return {
      e: this.centerE + (x - this.width / 2) / this.scale,
      n: this.centerN - (y - this.height / 2) / this.scale,
    };
  }

  setView(e, n, scale) {
    this.centerE = e;
    this.centerN = n;
    this.scale = Math.min(Math.max(scale, 1e-4), 1e3);
    this.onChange();
  }

  // Show the box (UTM metres) whole, with a margin.
  fit(west, south, east, north) {
    const w = Math.max(east - west, 1), h = Math.max(north - south, 1);
    const scale = 0.9 * Math.min(this.width / w, this.height / h);
    this.setView((west + east) / 2, (south + north) / 2, scale);
  }

  zoomAt(x, y, factor) {
    const at = this.screenToUtm(x, y);
    const scale = Math.min(Math.max(this.scale * factor, 1e-4), 1e3);
    // Keep the point under (x, y) where it is.
    this.setView(
      at.e - (x - this.width / 2) / scale,
      at.n + (y - this.height / 2) / scale,
      scale,
    );
  }

  panBy(dx, dy) {
    this.setView(this.centerE - dx / this.scale, this.centerN + dy / this.scale, this.scale);
  }

  // --- canvas ------------------------------------------------------------------------------

  _resize() {
    const rect = this.canvas.getBoundingClientRect();
    this.dpr = window.devicePixelRatio || 1;
    this.width = Math.max(rect.width, 1);
    this.height = Math.max(rect.height, 1);
    this.canvas.width = Math.round(this.width * this.dpr);
    this.canvas.height = Math.round(this.height * this.dpr);
    this.onChange();
  }

  // Start a frame: clear, CSS-pixel coordinates.
  begin() {
    const ctx = this.ctx;
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = "#0c1d2b";
    ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    ctx.setTransform(this.dpr, 0, 0, this.dpr, 0, 0);
    return ctx;
  }

  // Draw a tile image whose top-left corner is (west, north) and side `sideM` metres;
  // false when it lies off screen.
  drawTile(img, west, north, sideM, opacity) {
    return this.drawImage(img, west, north, sideM, sideM, opacity);
  }

  // Draw a north-up image whose top-left corner is (west, north), `widthM` by `heightM`
  // metres; false when it lies off screen.
  drawImage(img, west, north, widthM, heightM, opacity) {
    const p = this.utmToScreen(west, north);
    const w = widthM * this.scale, h = heightM * this.scale;
    if (p.x > this.width || p.y > this.height || p.x + w < 0 || p.y + h < 0) return false;
    const ctx = this.ctx;
    // Zoomed in (an image pixel covers a screen pixel or more): nearest neighbour, so
    // the values drawn are the image's.
    ctx.imageSmoothingEnabled = w * this.dpr < (img.naturalWidth || img.width);
    ctx.globalAlpha = opacity;
    ctx.drawImage(img, p.x, p.y, w, h);
    ctx.globalAlpha = 1;
    return true;
  }

  // Draw polygons, each a list of rings of [east, north] (UTM metres; holes are rings
  // too: filled even-odd), filled with `fill` and outlined with `stroke`, dashed by `dash`.
  drawPolygons(polygons, fill, stroke, dash) {
    const ctx = this.ctx;
    ctx.save();
    ctx.lineWidth = 2;
    ctx.lineJoin = "round";
    ctx.setLineDash(dash);
    for (const rings of polygons) {
      ctx.beginPath();
      for (const ring of rings) {
        ring.forEach(([e, n], i) => {
          const p = this.utmToScreen(e, n);
          if (i === 0) ctx.moveTo(p.x, p.y);
          else ctx.lineTo(p.x, p.y);
        });
        ctx.closePath();
      }
      ctx.fillStyle = fill;
      ctx.fill("evenodd");
      ctx.strokeStyle = stroke;
      ctx.stroke();
    }
    ctx.restore();
  }

  drawTrack(points, colour) {
    if (points.length < 2) return;
    const ctx = this.ctx;
    ctx.beginPath();
    for (let i = 0; i < points.length; i++) {
      const p = this.utmToScreen(points[i][0], points[i][1]);
      if (i === 0) ctx.moveTo(p.x, p.y);
      else ctx.lineTo(p.x, p.y);
    }
    ctx.strokeStyle = colour;
    ctx.globalAlpha = 0.75; // lighter than the boat drawn on it
    ctx.lineWidth = 2;
    ctx.lineJoin = "round";
    ctx.stroke();
    ctx.globalAlpha = 1;
  }

  // A boat: an arrow at (e, n) pointing along `gridBearingDeg` (clockwise from grid north,
  // that is from screen up), grey and dashed when away.
  drawBoat(e, n, gridBearingDeg, colour, label, away) {
    const ctx = this.ctx;
    const p = this.utmToScreen(e, n);
    ctx.save();
    ctx.translate(p.x, p.y);
    ctx.rotate((gridBearingDeg * Math.PI) / 180);
    ctx.beginPath();
    ctx.moveTo(0, -14);
    ctx.lineTo(9, 10);
    ctx.lineTo(0, 5);
    ctx.lineTo(-9, 10);
    ctx.closePath();
    ctx.fillStyle = away ? "#8a8f96" : colour;
    ctx.fill();
    ctx.setLineDash(away ? [3, 3] : []);
    ctx.lineWidth = 2;
    ctx.strokeStyle = "#ffffff";
    ctx.stroke();
    ctx.restore();
    ctx.font = "13px system-ui, sans-serif";
    ctx.lineWidth = 3;
    ctx.strokeStyle = "rgba(0,0,0,0.7)";
    const text = away ? `${label} (away)` : label;
    ctx.strokeText(text, p.x + 14, p.y - 10);
    ctx.fillStyle = "#ffffff";
    ctx.fillText(text, p.x + 14, p.y - 10);
  }

  // The length (metres) of a scale bar about `targetPx` long: 1, 2 or 5 times a power of 10.
  scaleBar(targetPx) {
    const metres = targetPx / this.scale;
    const power = Math.pow(10, Math.floor(Math.log10(metres)));
    const nice = [5, 2, 1].map((k) => k * power).find((m) => m <= metres) || power;
    return { metres: nice, px: nice * this.scale };
  }

  // --- input: mouse wheel and drag, touch pan and pinch (pointer events) -------------------

  _listen() {
    const c = this.canvas;
    c.addEventListener("wheel", (ev) => {
      ev.preventDefault();
      const r = c.getBoundingClientRect();
      const step = ev.deltaMode === 1 ? ev.deltaY * 33 : ev.deltaY;
      this.touched = true;
      this.zoomAt(ev.clientX - r.left, ev.clientY - r.top, Math.exp(-step * 0.0015));
    }, { passive: false });
    c.addEventListener("pointerdown", (ev) => {
      c.setPointerCapture(ev.pointerId);
      this._pointers.set(ev.pointerId, this._local(ev));
      this._gesture = null;
      this._move(); // the gesture's start, from where each pointer is now
    });
    c.addEventListener("pointermove", (ev) => {
      const here = this._local(ev);
      this.onPointer(here.x, here.y);
      if (!this._pointers.has(ev.pointerId)) return;
      this._pointers.set(ev.pointerId, here);
      this._move();
    });
    const up = (ev) => {
      this._pointers.delete(ev.pointerId);
      this._gesture = null;
      if (this._pointers.size) this._move(); // a pinch becomes a pan: restart from here
    };
    c.addEventListener("pointerup", up);
    c.addEventListener("pointercancel", up);
    c.addEventListener("pointerleave", () => this.onPointer(null, null));
  }

  _local(ev) {
    const r = this.canvas.getBoundingClientRect();
    return { x: ev.clientX - r.left, y: ev.clientY - r.top };
  }

  // One pointer pans; two pan by their midpoint and zoom by their spread.
  _move() {
    const pts = [...this._pointers.values()].slice(0, 2);
    const mid = {
      x: pts.reduce((s, p) => s + p.x, 0) / pts.length,
      y: pts.reduce((s, p) => s + p.y, 0) / pts.length,
    };
    const spread = pts.length === 2 ? Math.hypot(pts[0].x - pts[1].x, pts[0].y - pts[1].y) : 0;
    const last = this._gesture;
    this._gesture = { mid, spread, count: pts.length };
    if (!last || last.count !== pts.length) return;
    this.touched = true;
    this.panBy(mid.x - last.mid.x, mid.y - last.mid.y);
    if (pts.length === 2 && last.spread > 0 && spread > 0) {
      this.zoomAt(mid.x, mid.y, spread / last.spread);
    }
  }
}
