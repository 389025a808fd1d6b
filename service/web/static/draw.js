// Hand-written 2D drawing: a growing pose buffer, trajectory views and small time plots.
// Long runs stay cheap: new poses are drawn onto a kept layer (only a change of scale redraws
// everything), and a full redraw skips vertices closer than a pixel to the previous one.

const STATUS = { o: 0, d: 1, l: 2 };
export const STATUS_NAMES = ["ok", "degraded", "lost"];
const COLORS = { path: "#2563eb", front: "#9aa3b2", smoothed: "#16a34a", degraded: "#e08a00", lost: "#d62828",
                 grid: "#e6e9ef", text: "#6b7280", now: "#111827" };

// Column store of every pose received; typed arrays grow by doubling.
export class PoseBuffer {
  constructor() {
    this.n = 0;
    this.capacity = 0;
    this.grow(1024);
  }

  grow(capacity) {
    const resize = (old, Type, width) => {
      const array = new Type(capacity * width);
      if (old) array.set(old.subarray(0, this.n * width));
      return array;
    };
    this.index = resize(this.index, Float64Array, 1);
    this.time = resize(this.time, Float64Array, 1);  // seconds since the first pose
    this.position = resize(this.position, Float64Array, 3);
    this.front = resize(this.front, Float64Array, 3);
    this.forward = resize(this.forward, Float32Array, 3);
    this.status = resize(this.status, Uint8Array, 1);
    this.inliers = resize(this.inliers, Float32Array, 1);
    this.latency = resize(this.latency, Float32Array, 1);
    this.capacity = capacity;
  }

  // Append one ``poses`` message (columns); returns the number of poses added.
  append(message) {
    const count = message.index.length;
    if (this.n + count > this.capacity) {
      this.grow(Math.max(this.capacity * 2, this.n + count));
    }
    if (this.t0 === undefined && count) this.t0 = message.timestamp_ns[0];
    for (let k = 0; k < count; k++) {
      const i = this.n + k;
      this.index[i] = message.index[k];
      this.time[i] = (message.timestamp_ns[k] - this.t0) * 1e-9;
      for (let a = 0; a < 3; a++) {
        this.position[3 * i + a] = message.position[3 * k + a];
        this.front[3 * i + a] = message.frontend_position[3 * k + a];
        this.forward[3 * i + a] = message.forward[3 * k + a];
      }
      this.status[i] = STATUS[message.status[k]] ?? 2;
      this.inliers[i] = message.inliers[k];
      this.latency[i] = message.latency_ms[k];
    }
    this.n += count;
    return count;
  }

  count(status) {
    let total = 0;
    for (let i = 0; i < this.n; i++) total += this.status[i] === status;
    return total;
  }
}

// Positions only (the smoother's final poses), growing by doubling.
export class PathBuffer {
  constructor() {
    this.n = 0;
    this.position = new Float64Array(3 * 1024);
  }

  append(flat) {
    const count = flat.length / 3;
    if (3 * (this.n + count) > this.position.length) {
      const grown = new Float64Array(Math.max(2 * this.position.length, 3 * (this.n + count)));
      grown.set(this.position.subarray(0, 3 * this.n));
      this.position = grown;
    }
    this.position.set(flat, 3 * this.n);
    this.n += count;
  }
}

function fitCanvas(canvas) {
  const ratio = window.devicePixelRatio || 1;
  const width = Math.max(1, Math.round(canvas.clientWidth * ratio));
  const height = Math.max(1, Math.round(canvas.clientHeight * ratio));
  if (canvas.width !== width || canvas.height !== height) {
    canvas.width = width;
    canvas.height = height;
    return true;
  }
  return false;
}

function niceStep(span) {
  const raw = span / 5;
  const power = 10 ** Math.floor(Math.log10(raw));
  return [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw);
}

// One projection of the trajectory: world axes ``axes`` = [[axis, sign] horizontal, vertical].
export class TrajectoryView {
  constructor(canvas, buffer, axes, labels, smoothed) {
    this.canvas = canvas;
    this.buffer = buffer;
    this.smoothed = smoothed;  // a PathBuffer drawn on top
    this.drawnSmoothed = 0;
    this.axes = axes;
    this.labels = labels;
    this.layer = document.createElement("canvas");
    this.drawn = 0;        // poses already on the layer
    this.vertices = 0;     // vertices drawn (after decimation) for the fused path
    this.redraws = 0;      // full redraws (a change of scale or size)
    this.bounds = null;
  }

  // A new projection: everything is drawn again at the next update. With ``across`` (a list
  // of [axis, sign, label]) the horizontal axis is whichever of them the path spans most.
  setAxes(axes, labels, across = null) {
    this.axes = axes;
    this.labels = labels;
    this.across = across;
    this.bounds = null;
  }

  chooseAcross() {
    const b = this.buffer;
    let best = null;
    for (const [axis, sign, label] of this.across) {
      let low = Infinity;
      let high = -Infinity;
      for (let i = 0; i < b.n; i++) {
        low = Math.min(low, b.position[3 * i + axis]);
        high = Math.max(high, b.position[3 * i + axis]);
      }
      if (!best || high - low > best.span) best = { span: high - low, axis, sign, label };
    }
    const changed = best.axis !== this.axes[0][0];
    this.axes = [[best.axis, best.sign], this.axes[1]];
    this.labels = [best.label, this.labels[1]];
    return changed;
  }

  coord(array, i, which) {
    const [axis, sign] = this.axes[which];
    return sign * array[3 * i + axis];
  }

  // Equal scale on both axes; bounds grow with a margin so a moving robot rarely forces a redraw.
  fit(from) {
    const b = this.buffer;
    let [u0, u1, v0, v1] = this.bounds ?? [Infinity, -Infinity, Infinity, -Infinity];
    const take = (array, i) => {
      const u = this.coord(array, i, 0);
      const v = this.coord(array, i, 1);
      u0 = Math.min(u0, u); u1 = Math.max(u1, u); v0 = Math.min(v0, v); v1 = Math.max(v1, v);
    };
    for (let i = from; i < b.n; i++) {
      take(b.position, i);
      take(b.front, i);
    }
    for (let i = from ? this.drawnSmoothed : 0; i < this.smoothed.n; i++) {
      take(this.smoothed.position, i);
    }
    const span = Math.max(u1 - u0, v1 - v0, 0.5);
    const margin = 0.15 * span;
    this.bounds = [u0 - margin, u1 + margin, v0 - margin, v1 + margin];
    const [w, h] = [this.layer.width, this.layer.height];
    const pad = 28 * (window.devicePixelRatio || 1);
    this.scale = Math.min((w - 2 * pad) / (this.bounds[1] - this.bounds[0]),
                          (h - 2 * pad) / (this.bounds[3] - this.bounds[2]));
    this.cu = (this.bounds[0] + this.bounds[1]) / 2;
    this.cv = (this.bounds[2] + this.bounds[3]) / 2;
  }

  inside(i, arrays = [this.buffer.position, this.buffer.front]) {
    const [u0, u1, v0, v1] = this.bounds;
    for (const array of arrays) {
      const u = this.coord(array, i, 0);
      const v = this.coord(array, i, 1);
      if (u < u0 || u > u1 || v < v0 || v > v1) return false;
    }
    return true;
  }

  px(array, i) {
    return [this.layer.width / 2 + (this.coord(array, i, 0) - this.cu) * this.scale,
            this.layer.height / 2 - (this.coord(array, i, 1) - this.cv) * this.scale];
  }

  // Bring the drawing up to date with the buffer; returns true when anything changed.
  update() {
    const b = this.buffer;
    const resized = fitCanvas(this.canvas);
    if (resized) {
      this.layer.width = this.canvas.width;
      this.layer.height = this.canvas.height;
    }
    if (b.n === 0) return false;
    let full = resized || this.bounds === null;
    if (!full) {
      for (let i = this.drawn; i < b.n && !full; i++) full = !this.inside(i);
      for (let i = this.drawnSmoothed; i < this.smoothed.n && !full; i++) {
        full = !this.inside(i, [this.smoothed.position]);
      }
    }
    if (!full && this.drawn === b.n && this.drawnSmoothed === this.smoothed.n) return false;
    if (full) {
      if (this.across && this.chooseAcross()) this.bounds = null;
      this.fit(this.bounds === null || resized ? 0 : this.drawn);
      this.redrawAll();
    } else {
      this.drawFrom(this.drawn, this.drawnSmoothed);
    }
    this.drawn = b.n;
    this.drawnSmoothed = this.smoothed.n;
    this.compose();
    return true;
  }

  redrawAll() {
    const ctx = this.layer.getContext("2d");
    ctx.clearRect(0, 0, this.layer.width, this.layer.height);
    this.drawGrid(ctx);
    this.redraws += 1;
    this.vertices = 0;
    this.last = null;
    this.lastFront = null;
    this.lastSmoothed = null;
    this.drawFrom(0, 0);
  }

  drawFrom(start, startSmoothed) {
    const ctx = this.layer.getContext("2d");
    const b = this.buffer;
    const ratio = window.devicePixelRatio || 1;
    const line = (array, lastKey, color, width, from = start, n = b.n) => {
      ctx.beginPath();
      ctx.strokeStyle = color;
      ctx.lineWidth = width * ratio;
      ctx.lineJoin = "round";
      let last = this[lastKey];
      if (last) ctx.moveTo(last[0], last[1]);
      let drawn = 0;
      for (let i = from; i < n; i++) {
        const p = this.px(array, i);
        // Decimation: a vertex within a pixel of the previous one adds nothing visible.
        if (last && Math.abs(p[0] - last[0]) < ratio && Math.abs(p[1] - last[1]) < ratio
            && i < n - 1) continue;
        if (last) ctx.lineTo(p[0], p[1]); else ctx.moveTo(p[0], p[1]);
        last = p;
        drawn += 1;
      }
      ctx.stroke();
      this[lastKey] = last;
      return drawn;
    };
    line(b.front, "lastFront", COLORS.front, 1);
    this.vertices += line(b.position, "last", COLORS.path, 2);
    line(this.smoothed.position, "lastSmoothed", COLORS.smoothed, 1.5, startSmoothed,
         this.smoothed.n);
    // Degraded and lost frames are few and always shown (never decimated away).
    for (let i = start; i < b.n; i++) {
      if (b.status[i] === 0) continue;
      const [x, y] = this.px(b.position, i);
      ctx.fillStyle = b.status[i] === 1 ? COLORS.degraded : COLORS.lost;
      ctx.beginPath();
      ctx.arc(x, y, (b.status[i] === 1 ? 3 : 4) * ratio, 0, 2 * Math.PI);
      ctx.fill();
    }
  }

  drawGrid(ctx) {
    const ratio = window.devicePixelRatio || 1;
    const [w, h] = [this.layer.width, this.layer.height];
    const step = niceStep(w / this.scale);
    ctx.strokeStyle = COLORS.grid;
    ctx.lineWidth = ratio;
    ctx.fillStyle = COLORS.text;
    ctx.font = `${11 * ratio}px sans-serif`;
    const u0 = this.cu - w / 2 / this.scale;
    const v0 = this.cv - h / 2 / this.scale;
    for (let u = Math.ceil(u0 / step) * step; u < u0 + w / this.scale; u += step) {
      const x = w / 2 + (u - this.cu) * this.scale;
      ctx.beginPath(); ctx.moveTo(x, 0); ctx.lineTo(x, h); ctx.stroke();
    }
    for (let v = Math.ceil(v0 / step) * step; v < v0 + h / this.scale; v += step) {
      const y = h / 2 - (v - this.cv) * this.scale;
      ctx.beginPath(); ctx.moveTo(0, y); ctx.lineTo(w, y); ctx.stroke();
    }
    const label = step >= 1 ? `${step} m` : `${Math.round(step * 100)} cm`;
    ctx.fillText(`grid ${label}`, 8 * ratio, h - 8 * ratio);
    ctx.fillText(this.labels[0], w - ctx.measureText(this.labels[0]).width - 8 * ratio,
                 h - 8 * ratio);
    ctx.fillText(this.labels[1], 8 * ratio, 16 * ratio);
  }

  // The kept layer plus the newest pose and its heading.
  compose() {
    const ctx = this.canvas.getContext("2d");
    const b = this.buffer;
    const ratio = window.devicePixelRatio || 1;
    ctx.clearRect(0, 0, this.canvas.width, this.canvas.height);
    ctx.drawImage(this.layer, 0, 0);
    if (b.n === 0) return;
    const i = b.n - 1;
    const [x, y] = this.px(b.position, i);
    const du = this.coord(b.forward, i, 0);
    const dv = this.coord(b.forward, i, 1);
    const norm = Math.hypot(du, dv);
    ctx.strokeStyle = COLORS.now;
    ctx.lineWidth = 2 * ratio;
    if (norm > 0.2) {
      ctx.beginPath();
      ctx.moveTo(x, y);
      ctx.lineTo(x + (du / norm) * 18 * ratio, y - (dv / norm) * 18 * ratio);
      ctx.stroke();
    }
    ctx.fillStyle = COLORS.now;
    ctx.beginPath();
    ctx.arc(x, y, 4.5 * ratio, 0, 2 * Math.PI);
    ctx.fill();
  }
}

// A small plot of one quantity over the last ``window`` values; min/max per pixel column.
export class TimePlot {
  constructor(canvas, label, unit, { window = 1200, color = "#2563eb", digits = 0 } = {}) {
    this.canvas = canvas;
    this.label = label;
    this.unit = unit;
    this.window = window;
    this.color = color;
    this.digits = digits;
    this.values = new Float32Array(window);  // ring buffer
    this.count = 0;
    this.dirty = true;
  }

  push(value) {
    this.values[this.count % this.window] = value;
    this.count += 1;
    this.dirty = true;
  }

  value(k) {  // k-th of the kept values, oldest first
    const start = Math.max(0, this.count - this.window);
    return this.values[(start + k) % this.window];
  }

  draw() {
    if (!this.dirty && !fitCanvas(this.canvas)) return;
    fitCanvas(this.canvas);
    this.dirty = false;
    const ctx = this.canvas.getContext("2d");
    const ratio = window.devicePixelRatio || 1;
    const [w, h] = [this.canvas.width, this.canvas.height];
    const top = 20 * ratio;
    const bottom = h - 6 * ratio;
    ctx.clearRect(0, 0, w, h);
    ctx.font = `${11 * ratio}px sans-serif`;
    ctx.fillStyle = COLORS.text;
    const kept = Math.min(this.count, this.window);
    let high = 0;
    for (let k = 0; k < kept; k++) high = Math.max(high, this.value(k));
    high = high > 0 ? high * 1.1 : 1;
    const latest = kept ? this.value(kept - 1).toFixed(this.digits) : "—";
    ctx.fillText(`${this.label}: ${latest} ${this.unit}`, 4 * ratio, 13 * ratio);
    const scaleText = `max ${high.toFixed(this.digits)}`;
    ctx.fillText(scaleText, w - ctx.measureText(scaleText).width - 4 * ratio, 13 * ratio);
    ctx.strokeStyle = COLORS.grid;
    ctx.beginPath(); ctx.moveTo(0, bottom); ctx.lineTo(w, bottom); ctx.stroke();
    if (!kept) return;
    const y = (v) => bottom - (v / high) * (bottom - top);
    ctx.strokeStyle = this.color;
    ctx.lineWidth = 1.5 * ratio;
    ctx.beginPath();
    const columns = Math.max(1, Math.floor(w));
    if (kept <= columns) {
      for (let k = 0; k < kept; k++) {
        const x = kept === 1 ? w : (k / (kept - 1)) * w;
        if (k === 0) ctx.moveTo(x, y(this.value(k))); else ctx.lineTo(x, y(this.value(k)));
      }
    } else {
      for (let c = 0; c < columns; c++) {
        const k0 = Math.floor((c * kept) / columns);
        const k1 = Math.max(k0 + 1, Math.floor(((c + 1) * kept) / columns));
        let lo = Infinity;
        let hi = -Infinity;
        for (let k = k0; k < k1; k++) {
          const v = this.value(k);
          lo = Math.min(lo, v); hi = Math.max(hi, v);
        }
        ctx.moveTo(c + 0.5, y(lo)); ctx.lineTo(c + 0.5, Math.min(y(hi), y(lo) - 1));
      }
    }
    ctx.stroke();
  }
}
