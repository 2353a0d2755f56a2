// The top-down map: the renderer's orthographic picture of the scene, the flyable box, the spray deposit
// (a run with spraying: under everything else, toggleable), every vehicle with its heading (in a fleet:
// each in its own colour, with its name), their trails and active goals.
// A click reports the world x, y under the pointer, and the vehicle drawn there if any.

import { withToken } from "./connection.js";
import { painter } from "./painter.js";

const TRAIL_POINTS = 600;
const DRAW_MS = 250; // the vehicles move on the map at most 4 times a second
const HIT_PX = 12; // a click this close to a vehicle (screen pixels) is a click on it
// where a vehicle's name goes (left of the text's middle, from the vehicle), first the first that is free
const LABEL_SPOTS = [[16, -10], [16, 6], [16, -24], [16, 20], [-16, -10], [-16, 6]];
// one vehicle: cyan arrow, yellow trail, red goal; a fleet: everything of a vehicle in its colour
const SINGLE = { arrow: "#00e5ff", trail: "rgba(255, 220, 60, 0.9)", goal: "#ff4d6d" };
export const FLEET_COLOURS = [
  "#00e5ff", "#ffb000", "#ff5dce", "#7cff6b", "#b18cff", "#ff7a45", "#4d9dff", "#fffb5c",
];

export class MapView {
  constructor(canvas, onClick) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.image = null;
    this.meta = null;
    this.names = []; // the vehicles in the API's order; more than one: a fleet
    this.vehicles = new Map(); // name -> {x, y, yaw, trail, goal}
    this.selected = null; // the vehicle the goal getter and the highlight follow
    this.background = null; // the map picture with the flyable box, drawn once per scene
    this.deposit = null; // the spray deposit layer (deposit.js), or null
    this.showDeposit = true;
    this.drawnAt = 0;
    this.drawTimer = 0;
    canvas.addEventListener("click", (e) => {
      if (!this.meta) return;
      const r = canvas.getBoundingClientRect();
      const u = ((e.clientX - r.left) * canvas.width) / r.width;
      const v = ((e.clientY - r.top) * canvas.height) / r.height;
      const [x, y] = this.toWorld(u, v);
      onClick(x, y, this.vehicleAt(u, v, (HIT_PX * canvas.width) / r.width));
    });
  }

  get fleet() {
    return this.names.length > 1;
  }

  // The vehicles to draw, in the API's order (the first is the default vehicle).
  setVehicles(names, selected) {
    this.names = names;
    for (const name of [...this.vehicles.keys()]) if (!names.includes(name)) this.vehicles.delete(name);
    this.select(selected);
  }

  select(name) {
    this.selected = name;
    this.requestDraw();
  }

  colour(name) {
    return FLEET_COLOURS[Math.max(0, this.names.indexOf(name)) % FLEET_COLOURS.length];
  }

  style(name) {
    if (!this.fleet) return SINGLE;
    const c = this.colour(name);
    return { arrow: c, trail: c, goal: c };
  }

  entry(name) {
    let v = this.vehicles.get(name);
    if (!v) {
      v = { x: 0, y: 0, yaw: 0, seen: false, trail: [], goal: null };
      this.vehicles.set(name, v);
    }
    return v;
  }

  // the selected vehicle's active goal (the one vehicle's, without a fleet)
  get goal() {
    return this.vehicles.get(this.selected)?.goal ?? null;
  }

  async load(scene, seed) {
    const res = await fetch(withToken(`/api/map/${encodeURIComponent(scene)}?seed=${seed}`));
    const meta = await res.json();
    if (!res.ok) throw new Error(meta.error || `map of ${scene}: HTTP ${res.status}`);
    const img = new Image();
    img.src = withToken(meta.image);
    await img.decode();
    const [x0, y0, x1, y1] = meta.extent;
    // one canvas pixel per screen pixel: the compositor then copies the map instead of resampling it
    const width = Math.round(this.canvas.clientWidth * devicePixelRatio) || 400;
    this.canvas.width = width;
    this.canvas.height = Math.round((width * (y1 - y0)) / (x1 - x0));
    this.image = img;
    this.meta = meta;
    this.background = this.drawBackground();
    for (const v of this.vehicles.values()) {
      v.trail = [];
      v.goal = null;
    }
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

  // The vehicle drawn nearest canvas point (u, v) within `radius` canvas pixels, or null.
  vehicleAt(u, v, radius) {
    let best = null;
    let bestD = radius;
    for (const [name, s] of this.vehicles) {
      if (!s.seen) continue;
      const [a, b] = this.toCanvas(s.x, s.y);
      const d = Math.hypot(a - u, b - v);
      if (d <= bestD) [best, bestD] = [name, d];
    }
    return best;
  }

  setState(name, state) {
    const [x, y] = state.position;
    const s = this.entry(name);
    Object.assign(s, { x, y, yaw: state.yaw, seen: true });
    const last = s.trail[s.trail.length - 1];
    if (!last || Math.hypot(last[0] - x, last[1] - y) > 0.05) {
      s.trail.push([x, y]);
      if (s.trail.length > TRAIL_POINTS) s.trail.shift();
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

  // The spray deposit layer to draw (decodeDeposit's), or null for none.
  setDeposit(layer) {
    this.deposit = layer;
    this.requestDraw();
  }

  setShowDeposit(on) {
    this.showDeposit = on;
    this.requestDraw();
  }

  // The deposit picture in the world frame: its row 0 lies at the grid's lowest y, the bottom of the map.
  drawDeposit() {
    const { ctx } = this;
    const { canvas, extent } = this.deposit;
    const [u0, v0] = this.toCanvas(extent[0], extent[1]);
    const [u1, v1] = this.toCanvas(extent[2], extent[3]);
    ctx.save();
    ctx.translate(u0, v0);
    ctx.scale((u1 - u0) / canvas.width, (v1 - v0) / canvas.height);
    ctx.drawImage(canvas, 0, 0);
    ctx.restore();
  }

  clearTrail(name) {
    const s = this.vehicles.get(name);
    if (s) s.trail = [];
    this.draw();
  }

  setGoal(goal, name = this.selected) {
    if (name === null) return;
    this.entry(name).goal = goal;
    this.draw();
  }

  draw() {
    const { ctx, canvas } = this;
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    if (!this.meta) return;
    ctx.drawImage(this.background, 0, 0);
    if (this.deposit && this.showDeposit) this.drawDeposit();
    // the selected vehicle last: on top of the others
    const order = [...this.vehicles.keys()].sort((a, b) => (a === this.selected) - (b === this.selected));
    for (const name of order) this.drawTrail(name);
    for (const name of order) this.drawGoal(name);
    for (const name of order) this.drawVehicle(name);
    if (this.fleet) {
      const placed = [];
      for (const name of order.reverse()) this.drawLabel(name, placed);
    }
  }

  drawTrail(name) {
    const { ctx } = this;
    const { trail } = this.vehicles.get(name);
    if (trail.length < 2) return;
    ctx.strokeStyle = this.style(name).trail;
    ctx.globalAlpha = this.fleet && name !== this.selected ? 0.6 : 1;
    ctx.lineWidth = 2;
    ctx.beginPath();
    trail.forEach(([x, y], i) => {
      const [u, v] = this.toCanvas(x, y);
      if (i === 0) ctx.moveTo(u, v);
      else ctx.lineTo(u, v);
    });
    ctx.stroke();
    ctx.globalAlpha = 1;
  }

  drawGoal(name) {
    const { ctx } = this;
    const { goal } = this.vehicles.get(name);
    if (!goal) return;
    const [u, v] = this.toCanvas(goal[0], goal[1]);
    ctx.strokeStyle = this.style(name).goal;
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.arc(u, v, 7, 0, 2 * Math.PI);
    ctx.moveTo(u - 11, v);
    ctx.lineTo(u + 11, v);
    ctx.moveTo(u, v - 11);
    ctx.lineTo(u, v + 11);
    ctx.stroke();
  }

  drawVehicle(name) {
    const { ctx } = this;
    const s = this.vehicles.get(name);
    if (!s.seen) return;
    const [u, v] = this.toCanvas(s.x, s.y);
    const selected = this.fleet && name === this.selected;
    ctx.save();
    ctx.translate(u, v);
    if (selected) {
      ctx.strokeStyle = "#ffffff";
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.arc(0, 0, 15, 0, 2 * Math.PI);
      ctx.stroke();
    }
    ctx.rotate(-s.yaw); // world yaw is counter-clockwise, canvas angles clockwise
    ctx.fillStyle = this.style(name).arrow;
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

  // The vehicle's name beside it, in its colour, clear of the names in `placed` ([x0, y0, x1, y1]).
  drawLabel(name, placed) {
    const { ctx } = this;
    const s = this.vehicles.get(name);
    if (!s.seen) return;
    const [u, v] = this.toCanvas(s.x, s.y);
    ctx.font = `${name === this.selected ? "bold " : ""}12px system-ui, sans-serif`;
    const w = ctx.measureText(name).width;
    const boxes = LABEL_SPOTS.map(([dx, dy]) => {
      const x = dx > 0 ? u + dx : u + dx - w;
      return [x, v + dy - 7, x + w, v + dy + 7];
    });
    const overlaps = (a) => placed.some((b) => a[0] < b[2] && b[0] < a[2] && a[1] < b[3] && b[1] < a[3]);
    const box = boxes.find((b) => !overlaps(b)) ?? boxes[0];
    placed.push(box);
    ctx.textBaseline = "middle";
    ctx.lineWidth = 3;
    ctx.strokeStyle = "rgba(0, 0, 0, 0.85)";
    ctx.fillStyle = this.colour(name);
    ctx.strokeText(name, box[0], box[1] + 7);
    ctx.fillText(name, box[0], box[1] + 7);
  }
}
