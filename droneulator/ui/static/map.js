// The top-down map: the renderer's orthographic picture of the scene, the flyable box, the vehicle with
// its heading, its trail and the active goal. A click reports the world x, y under the pointer.

import { painter } from "./painter.js";

const TRAIL_POINTS = 600;
const DRAW_MS = 250; // the vehicle moves on the map at most 4 times a second

export class MapView {
  constructor(canvas, onClick) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.image = null;
    this.meta = null;
    this.trail = [];
    this.vehicle = null;
    this.goal = null;
    this.background = null; // the map picture with the flyable box, drawn once per scene
    this.drawnAt = 0;
    this.drawTimer = 0;
    canvas.addEventListener("click", (e) => {
      if (!this.meta) return;
      const r = canvas.getBoundingClientRect();
      const [x, y] = this.toWorld(((e.clientX - r.left) * canvas.width) / r.width,
        ((e.clientY - r.top) * canvas.height) / r.height);
      onClick(x, y);
    });
  }

  async load(scene, seed) {
    const res = await fetch(`/api/map/${encodeURIComponent(scene)}?seed=${seed}`);
    const meta = await res.json();
    if (!res.ok) throw new Error(meta.error || `map of ${scene}: HTTP ${res.status}`);
    const img = new Image();
    img.src = meta.image;
    await img.decode();
    const [x0, y0, x1, y1] = meta.extent;
    // one canvas pixel per screen pixel: the compositor then copies the map instead of resampling it
    const width = Math.round(this.canvas.clientWidth * devicePixelRatio) || 400;
    this.canvas.width = width;
    this.canvas.height = Math.round((width * (y1 - y0)) / (x1 - x0));
    this.image = img;
    this.meta = meta;
    this.background = this.drawBackground();
    this.trail = [];
    this.goal = null;
    this.draw();
  }

  toCanvas(x, y) {
    const [x0, y0, x1, y1] = this.meta.extent;
    return [((x - x0) / (x1 - x0)) * this.canvas.width, ((y1 - y) / (y1 - y0)) * this.canvas.height];
  }

  toWorld(u, v) {
    const [x0, y0, x1, y1] = this.meta.extent;
    return [x0 + (u / this.canvas.width) * (x1 - x0), y1 - (v / this.canvas.height) * (y1 - y0)];
  }

  setState(state) {
    const [x, y] = state.position;
    this.vehicle = { x, y, yaw: state.yaw };
    const last = this.trail[this.trail.length - 1];
    if (!last || Math.hypot(last[0] - x, last[1] - y) > 0.05) {
      this.trail.push([x, y]);
      if (this.trail.length > TRAIL_POINTS) this.trail.shift();
    }
    this.requestDraw();
  }

  // Draw with the page's next paint, at most every DRAW_MS: the whole canvas is composited again each
  // time it changes.
  requestDraw() {
    if (this.drawTimer) return; // a draw is already due, and will show this state too
    const wait = Math.max(0, this.drawnAt + DRAW_MS - performance.now());
    this.drawTimer = setTimeout(() => {
      this.drawTimer = 0;
      this.drawnAt = performance.now();
      painter.add("map", () => this.draw());
    }, wait);
  }

  drawBackground() {
    const bg = document.createElement("canvas");
    bg.width = this.canvas.width;
    bg.height = this.canvas.height;
    const ctx = bg.getContext("2d");
    ctx.drawImage(this.image, 0, 0, bg.width, bg.height);
    // outside the flyable box: dimmed
    const [bx0, by1] = this.toCanvas(this.meta.bounds_min[0], this.meta.bounds_min[1]);
    const [bx1, by0] = this.toCanvas(this.meta.bounds_max[0], this.meta.bounds_max[1]);
    ctx.fillStyle = "rgba(0, 0, 0, 0.35)";
    ctx.fillRect(0, 0, bg.width, by0);
    ctx.fillRect(0, by1, bg.width, bg.height - by1);
    ctx.fillRect(0, by0, bx0, by1 - by0);
    ctx.fillRect(bx1, by0, bg.width - bx1, by1 - by0);
    ctx.strokeStyle = "rgba(255, 255, 255, 0.8)";
    ctx.setLineDash([6, 4]);
    ctx.lineWidth = 1;
    ctx.strokeRect(bx0, by0, bx1 - bx0, by1 - by0);
    return bg;
  }

  clearTrail() {
    this.trail = [];
    this.draw();
  }

  setGoal(goal) {
    this.goal = goal;
    this.draw();
  }

  draw() {
    const { ctx, canvas } = this;
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    if (!this.meta) return;
    ctx.drawImage(this.background, 0, 0);
    if (this.trail.length > 1) {
      ctx.strokeStyle = "rgba(255, 220, 60, 0.9)";
      ctx.lineWidth = 2;
      ctx.beginPath();
      this.trail.forEach(([x, y], i) => {
        const [u, v] = this.toCanvas(x, y);
        if (i === 0) ctx.moveTo(u, v);
        else ctx.lineTo(u, v);
      });
      ctx.stroke();
    }
    if (this.goal) {
      const [u, v] = this.toCanvas(this.goal[0], this.goal[1]);
      ctx.strokeStyle = "#ff4d6d";
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.arc(u, v, 7, 0, 2 * Math.PI);
      ctx.moveTo(u - 11, v);
      ctx.lineTo(u + 11, v);
      ctx.moveTo(u, v - 11);
      ctx.lineTo(u, v + 11);
      ctx.stroke();
    }
    if (this.vehicle) {
      const [u, v] = this.toCanvas(this.vehicle.x, this.vehicle.y);
      ctx.save();
      ctx.translate(u, v);
      ctx.rotate(-this.vehicle.yaw); // world yaw is counter-clockwise, canvas angles clockwise
      ctx.fillStyle = "#00e5ff";
      ctx.strokeStyle = "#002b33";
      ctx.lineWidth = 1.5;
      ctx.beginPath();
      ctx.moveTo(11, 0);
      ctx.lineTo(-7, 6);
      ctx.lineTo(-3, 0);
      ctx.lineTo(-7, -6);
      ctx.closePath();
      ctx.fill();
      ctx.stroke();
      ctx.restore();
    }
  }
}
