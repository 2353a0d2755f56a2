// Live camera views: for every camera of the watched vehicle's rig, its RGB, depth (with a metres scale)
// and segmentation (with the class legend). Each shown image is logged with its render stamp and the
// wall time it appeared, which the benchmark reads to measure the image latency.
//
// Images arrive as JPEG bytes and are decoded with WebCodecs' ImageDecoder straight from those bytes
// into a bitmap handed to the view's canvas ("bitmaprenderer": no copy, no repaint of the page). An
// <img> fed blob: URLs costs more than twice the CPU: every Blob is registered with the browser process
// and the image is decoded again to paint it; on a machine whose cores the simulation needs, that CPU
// is the simulation's (docs/ui.md). Browsers without ImageDecoder decode through createImageBitmap.

import { withToken } from "./connection.js";
import { painter } from "./painter.js";

const KIND_TITLES = { rgb: "RGB", depth: "Depth", seg: "Segmentation" };
const SHOWN_LOG = 2000;
// The UI server sends each round's images back to back, every header saying how many more follow
// (`more`). The paint waits for the round's last image (at most BURST_WAIT_MS after the one before it),
// so one round is one frame of the browser's compositor, not two or three (docs/ui.md).
const BURST_WAIT_MS = 50;

export class CameraViews {
  constructor(root, config) {
    this.root = root;
    this.config = config;
    this.tiles = new Map();
    this.shown = []; // {vehicle, cam, kind, stamp_ns, shown_ms, paint}
    this.count = 0;
    this.errors = 0; // images that could not be decoded
    this.burstTimer = 0; // while set, the paint waits for the rest of a burst
    this.burstWaitMs = config.burst_wait_ms ?? BURST_WAIT_MS; // the longest wait for a burst's next image
    this.vehicle = null; // whose images are shown (null: any)
    this.label = null; // the vehicle's name in the captions (a fleet), or null
    window.addEventListener("resize", () => this.tiles.forEach((t) => fit(t)));
  }

  // Show `vehicle`'s cameras from now on (its name in the captions when `label`): the views of another
  // vehicle are removed, and images of any other vehicle still on their way are ignored.
  setVehicle(vehicle, label) {
    if (vehicle === this.vehicle && label === this.label) return;
    this.vehicle = vehicle;
    this.label = label;
    for (const t of this.tiles.values()) t.next = null;
    this.tiles.clear();
    this.root.replaceChildren();
  }

  tile(cam, kind) {
    const key = `${cam}/${kind}`;
    let t = this.tiles.get(key);
    if (t) return t;
    const fig = document.createElement("figure");
    fig.className = `camera ${kind}`;
    fig.dataset.cam = cam;
    fig.dataset.kind = kind;
    const view = document.createElement("canvas");
    view.className = "view";
    view.setAttribute("role", "img");
    view.setAttribute("aria-label", `${cam} ${KIND_TITLES[kind]}`);
    const cap = document.createElement("figcaption");
    cap.innerHTML = `<b>${cam}</b> · ${KIND_TITLES[kind]}`;
    if (this.label) cap.prepend(Object.assign(document.createElement("b"), { textContent: this.label }), " · ");
    fig.append(view, cap);
    if (kind === "depth") {
      const scale = document.createElement("div");
      scale.className = "scale";
      scale.innerHTML = `<img src="${withToken("/api/depth_scale.png")}" alt="depth scale"><span>0 m</span>` +
        `<span>${(this.config.depth_max_m / 2).toFixed(0)} m</span><span>${this.config.depth_max_m.toFixed(0)} m+</span>`;
      fig.append(scale);
    }
    if (kind === "seg") {
      const legend = document.createElement("ul");
      legend.className = "legend";
      for (const c of this.config.legend) {
        const li = document.createElement("li");
        li.innerHTML = `<i style="background: rgb(${c.rgb.join(",")})"></i>${c.name}`;
        legend.append(li);
      }
      fig.append(legend);
    }
    // one row per camera, RGB / depth / segmentation left to right
    let row = this.root.querySelector(`.camera-row[data-cam="${CSS.escape(cam)}"]`);
    if (!row) {
      row = document.createElement("div");
      row.className = "camera-row";
      row.dataset.cam = cam;
      this.root.append(row);
    }
    row.append(fig);
    [...row.children]
      .sort((a, b) => Object.keys(KIND_TITLES).indexOf(a.dataset.kind) - Object.keys(KIND_TITLES).indexOf(b.dataset.kind))
      .forEach((el) => row.append(el));
    t = { fig, view, ctx: view.getContext("bitmaprenderer"), busy: false, next: null, pending: null };
    this.tiles.set(key, t);
    return t;
  }

  show(header, bytes) {
    if (this.vehicle && header.vehicle && header.vehicle !== this.vehicle) {
      if (!(header.more > 0)) this.releaseBurst();
      return;
    }
    if (header.more > 0) this.holdBurst();
    this.decode(header, bytes);
    if (!(header.more > 0)) this.releaseBurst();
  }

  // Hold the paint until the burst's last image has arrived (and been queued for decoding).
  holdBurst() {
    if (this.burstTimer) clearTimeout(this.burstTimer);
    else painter.expect();
    this.burstTimer = setTimeout(() => this.releaseBurst(), this.burstWaitMs);
  }

  releaseBurst() {
    if (!this.burstTimer) return;
    clearTimeout(this.burstTimer);
    this.burstTimer = 0;
    painter.done();
  }

  decode(header, bytes) {
    const t = this.tile(header.cam, header.kind);
    if (t.busy) {
      t.next = [header, bytes]; // newest wins: an older image still waiting is dropped
      return;
    }
    t.busy = true;
    painter.expect();
    decodeImage(bytes, header.mime).then((bitmap) => {
      if (t.pending) t.pending.close(); // decoded but never painted: replaced by a newer image
      t.pending = bitmap;
      painter.add(`${header.cam}/${header.kind}`, () => this.paint(t, header), true);
    }, (err) => {
      this.errors++;
      console.warn(`${header.cam} ${header.kind}: image not decoded: ${err}`);
    }).finally(() => {
      t.busy = false;
      painter.done();
      if (t.next) {
        const [h, b] = t.next;
        t.next = null;
        this.decode(h, b);
      }
    });
  }

  paint(t, header) {
    const bitmap = t.pending;
    t.pending = null;
    if (!bitmap) return;
    if (t.view.width !== bitmap.width || t.view.height !== bitmap.height) {
      t.view.width = bitmap.width;
      t.view.height = bitmap.height;
      fit(t);
    }
    t.ctx.transferFromImageBitmap(bitmap);
    this.count++;
    this.shown.push({ vehicle: header.vehicle, cam: header.cam, kind: header.kind,
      stamp_ns: header.stamp_ns, shown_ms: performance.timeOrigin + performance.now(), paint: painter.flushes });
    if (this.shown.length > SHOWN_LOG) this.shown.splice(0, this.shown.length - SHOWN_LOG);
  }
}

// Show a view at a whole multiple of its pixel size, the largest that fits its column (or shrunk to the
// column when even one pixel per pixel does not fit): a view at its own size is copied by the browser's
// compositor, and only scaled views cost it a resampling of every image.
function fit(t) {
  const room = t.fig.clientWidth;
  const k = Math.floor(room / t.view.width);
  t.view.style.width = k >= 1 ? `${k * t.view.width}px` : "100%";
}

// Decode JPEG or PNG bytes into an ImageBitmap.
async function decodeImage(bytes, mime) {
  if (typeof ImageDecoder === "undefined") return createImageBitmap(new Blob([bytes], { type: mime }));
  const decoder = new ImageDecoder({ data: bytes, type: mime });
  try {
    const { image } = await decoder.decode();
    try {
      return await createImageBitmap(image);
    } finally {
      image.close();
    }
  } finally {
    decoder.close();
  }
}
