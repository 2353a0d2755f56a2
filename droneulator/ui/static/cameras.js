// Live camera views: for every camera of the rig, its RGB, depth (with a metres scale) and segmentation
// (with the class legend). Each shown image is logged with its render stamp and the wall time it
// appeared, which the benchmark reads to measure the image latency.

const KIND_TITLES = { rgb: "RGB", depth: "Depth", seg: "Segmentation" };
const SHOWN_LOG = 2000;

export class CameraViews {
  constructor(root, config) {
    this.root = root;
    this.config = config;
    this.tiles = new Map();
    this.shown = []; // {cam, kind, stamp_ns, shown_ms}
    this.count = 0;
  }

  tile(cam, kind) {
    const key = `${cam}/${kind}`;
    let t = this.tiles.get(key);
    if (t) return t;
    const fig = document.createElement("figure");
    fig.className = `camera ${kind}`;
    fig.dataset.cam = cam;
    fig.dataset.kind = kind;
    const img = document.createElement("img");
    img.alt = `${cam} ${KIND_TITLES[kind]}`;
    const cap = document.createElement("figcaption");
    cap.innerHTML = `<b>${cam}</b> · ${KIND_TITLES[kind]}`;
    fig.append(img, cap);
    if (kind === "depth") {
      const scale = document.createElement("div");
      scale.className = "scale";
      scale.innerHTML = `<img src="/api/depth_scale.png" alt="depth scale"><span>0 m</span>` +
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
    t = { img, busy: false, next: null };
    this.tiles.set(key, t);
    return t;
  }

  show(header, blob) {
    const t = this.tile(header.cam, header.kind);
    if (t.busy) {
      t.next = [header, blob]; // newest wins: an older image still waiting is dropped
      return;
    }
    t.busy = true;
    const url = URL.createObjectURL(blob);
    const done = () => {
      if (t.url) URL.revokeObjectURL(t.url);
      t.url = url;
      t.busy = false;
      this.count++;
      this.shown.push({ cam: header.cam, kind: header.kind, stamp_ns: header.stamp_ns,
        shown_ms: performance.timeOrigin + performance.now() });
      if (this.shown.length > SHOWN_LOG) this.shown.splice(0, this.shown.length - SHOWN_LOG);
      if (t.next) {
        const [h, b] = t.next;
        t.next = null;
        this.show(h, b);
      }
    };
    const probe = new Image();
    probe.src = url;
    probe.decode().then(() => {
      t.img.src = url;
      done();
    }, () => {
      t.busy = false;
      URL.revokeObjectURL(url);
    });
  }
}
