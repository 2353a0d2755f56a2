// One paint for a burst of updates. Every change to what the page shows (a camera image, the map, the
// telemetry) is queued here and applied together in one animation frame: the UI server sends each
// stream's image back to back ten times a second, and painting them (plus the map) in one frame instead
// of one frame each keeps the browser's compositing, the largest part of its CPU, to one frame per
// burst (docs/ui.md).

const FALLBACK_MS = 150; // updates that do not come with images are painted this soon at the latest

export class Painter {
  constructor() {
    this.jobs = new Map(); // key -> function; a newer job under the same key replaces the older one
    this.frame = 0;
    this.timer = 0;
    this.waiting = 0; // updates on their way (images decoding): the burst's paint waits for them
    this.flushes = 0; // paints so far (the camera views log which paint showed each image)
  }

  // Queue `fn` for the next paint; `urgent` paints at the next animation frame, otherwise within
  // FALLBACK_MS (or with the next urgent paint, whichever comes first).
  add(key, fn, urgent = false) {
    this.jobs.set(key, fn);
    if (urgent) this.soon();
    else if (!this.timer && !this.frame) this.timer = setTimeout(() => this.soon(), FALLBACK_MS);
  }

  // An update is on its way; call done() when it has been queued (or has failed).
  expect() {
    this.waiting++;
  }

  done() {
    this.waiting = Math.max(0, this.waiting - 1);
    if (this.waiting === 0 && this.jobs.size) this.soon();
  }

  soon() {
    if (this.frame || this.waiting > 0) return;
    clearTimeout(this.timer);
    this.timer = 0;
    this.frame = requestAnimationFrame(() => this.flush());
  }

  flush() {
    this.frame = 0;
    this.flushes++;
    const jobs = [...this.jobs.values()];
    this.jobs.clear();
    for (const fn of jobs) fn();
  }
}

export const painter = new Painter();
