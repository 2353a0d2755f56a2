// The spray deposit layer of the map (docs/spray.md): the API's `spray_deposit` reply (the ground
// deposit's levels, 0 where nothing landed and 1..100 over log10 of 1e-4..10 uL/cm^2, as a greyscale
// PNG, one pixel a cell, row 0 at the grid's origin) turned into a coloured, half-transparent picture
// the map draws in the world frame. A reply that does not fit (a wrong size, a PNG that does not
// decode) is refused with an Error, and the map keeps what it had.

// the colour ramp over the levels 1..100 (log scale), matplotlib's "plasma": violet for traces, yellow
// for the heaviest deposit; no green, which the map's grass and canopies would swallow
export const DEPOSIT_STOPS = [
  [1, [13, 8, 135]], [25, [126, 3, 168]], [50, [204, 71, 120]], [75, [248, 149, 64]], [100, [240, 249, 33]],
];
const ALPHA = 215; // of a cell where something landed; 0 elsewhere
const MAX_SIDE = 8192; // cells along a side: anything larger is not a deposit grid of this simulator

// RGBA of every level 0..255 (above 100: as 100), in one table
const LUT = (() => {
  const lut = new Uint8ClampedArray(256 * 4);
  for (let level = 1; level < 256; level++) {
    const l = Math.min(level, 100);
    const i = DEPOSIT_STOPS.findIndex(([at]) => at >= l);
    const [a, ca] = DEPOSIT_STOPS[Math.max(0, i - 1)];
    const [b, cb] = DEPOSIT_STOPS[i];
    const f = b > a ? (l - a) / (b - a) : 0;
    for (let k = 0; k < 3; k++) lut[level * 4 + k] = Math.round(ca[k] + f * (cb[k] - ca[k]));
    lut[level * 4 + 3] = ALPHA;
  }
  return lut;
})();

// The legend's CSS gradient, left (1e-4 uL/cm^2) to right (10 uL/cm^2).
export function legendGradient() {
  const stops = DEPOSIT_STOPS.map(([at, c]) => `rgb(${c.join(", ")}) ${(((at - 1) / 99) * 100).toFixed(0)}%`);
  return `linear-gradient(to right, ${stops.join(", ")})`;
}

const positiveInt = (v) => Number.isInteger(v) && v > 0 && v <= MAX_SIDE;
const finite = (v) => typeof v === "number" && Number.isFinite(v);

// Throws unless `d` is a `spray_deposit` reply with a picture the map can place.
function check(d) {
  const ok = d && typeof d === "object" && Number.isInteger(d.version) && positiveInt(d.width) &&
    positiveInt(d.height) && finite(d.cell_m) && d.cell_m > 0 && Array.isArray(d.origin) &&
    d.origin.length === 2 && d.origin.every(finite) && typeof d.png === "string";
  if (!ok) throw new Error("the deposit grid's reply is malformed");
}

// The layer of a `spray_deposit` reply: {version, t, canvas (one pixel a cell, row 0 at the origin's
// y), extent [x0, y0, x1, y1] (m), cells (where something landed), range_ul_cm2}.
export async function decodeDeposit(d) {
  check(d);
  let bitmap;
  try {
    const bytes = Uint8Array.from(atob(d.png), (c) => c.charCodeAt(0));
    const blob = new Blob([bytes], { type: "image/png" });
    bitmap = await createImageBitmap(blob, { premultiplyAlpha: "none", colorSpaceConversion: "none" });
  } catch (err) {
    throw new Error(`the deposit picture does not decode: ${err.message || err}`);
  }
  if (bitmap.width !== d.width || bitmap.height !== d.height) {
    bitmap.close();
    throw new Error(`the deposit picture is ${bitmap.width}x${bitmap.height}, not ${d.width}x${d.height}`);
  }
  const canvas = document.createElement("canvas");
  canvas.width = d.width;
  canvas.height = d.height;
  const ctx = canvas.getContext("2d", { willReadFrequently: true });
  ctx.drawImage(bitmap, 0, 0);
  bitmap.close();
  const img = ctx.getImageData(0, 0, d.width, d.height);
  const px = img.data;
  let cells = 0;
  for (let i = 0; i < px.length; i += 4) {
    const o = px[i] * 4; // grey: the level
    if (o) cells++;
    px[i] = LUT[o];
    px[i + 1] = LUT[o + 1];
    px[i + 2] = LUT[o + 2];
    px[i + 3] = LUT[o + 3];
  }
  ctx.putImageData(img, 0, 0);
  const [x0, y0] = d.origin;
  const extent = [x0, y0, x0 + d.width * d.cell_m, y0 + d.height * d.cell_m];
  return { version: d.version, t: d.t, canvas, extent, cells, range_ul_cm2: d.range_ul_cm2 };
}
