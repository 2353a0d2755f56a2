// Droneulator's browser UI: level select, then the flight view. Everything it does goes through the
// simulator's WebSocket API (relayed by the UI server) and every error the API returns is shown. In a
// world of several vehicles the flight controls, map clicks, telemetry and camera views follow the
// selected vehicle (docs/ui.md); the map shows them all. A run that sprays (docs/spray.md) shows each
// sprayer's spray state and draws the ground deposit on the map, asked for with `spray_deposit` once a
// second of sim time, only while a vehicle's state carries a spray system.

import { ApiError, Connection, TOKEN_KEY, withToken } from "./connection.js";
import { CameraViews } from "./cameras.js";
import { decodeDeposit, legendGradient } from "./deposit.js";
import { FLEET_COLOURS, MapView } from "./map.js";
import { painter } from "./painter.js";

const $ = (id) => document.getElementById(id);
const KEYS = {
  KeyW: "fwd", ArrowUp: "fwd", KeyS: "back", ArrowDown: "back",
  KeyA: "left", ArrowLeft: "left", KeyD: "right", ArrowRight: "right",
};
const YAW_RATE = 0.8; // rad/s while A/D is held
const EVENT_LOG = 60;
const RTF_WINDOW_MS = 3000;
const STATE_HZ = 5; // state messages per second: the map and the telemetry change at most 4 times a second
const TELEMETRY_MS = 250;
const DEPOSIT_EVERY_S = 1; // sim seconds between two asks for the deposit (the ROS grid's period)
const DEPOSIT_GIVE_UP_MS = 10000; // an ask unanswered this long (lost with a dropped API link) is dropped

const ui = {
  config: null,
  scene: null, // scene_info of the loaded scene
  light: null, // the light settings of the last level loaded here (reset's reply)
  vehicles: [], // scene_info's vehicles, the first the default one
  selected: null, // the vehicle the controls follow
  states: {}, // every vehicle's latest state, by name
  state: null, // the selected vehicle's latest state
  locks: {}, // why each vehicle's flight commands are refused (PX4 in control), by name
  locked: null, // the selected vehicle's lock, or null
  px4Status: {}, // PX4's status of each vehicle, by name
  keys: new Set(),
  lastVelocity: null,
  rtfSamples: [],
  images: null,
  apiConnected: false, // the UI server's link to the simulator's API, as it last reported it
  telemetryAt: 0,
  spray: false, // a vehicle's state carries a spray system: the deposit layer is shown
  deposit: { version: null, askedT: null, asking: 0, askedAt: 0, error: null, layer: null },
};
window.droneulatorUI = ui; // for tests and the benchmark

// ------------------------------------------------------------------------------------------------ errors
function showError(text) {
  const div = document.createElement("div");
  div.className = "error";
  div.textContent = text;
  const close = document.createElement("button");
  close.textContent = "×";
  close.title = "dismiss";
  close.onclick = () => div.remove();
  div.append(close);
  $("errors").prepend(div);
  while ($("errors").children.length > 4) $("errors").lastChild.remove();
  setTimeout(() => div.remove(), 15000);
}

function describe(err) {
  if (err instanceof ApiError) return `${err.message} (${err.code.replaceAll("_", " ")})`;
  return String(err.message || err);
}

// Send a request; on failure tell the person what the simulator said.
async function send(op, fields = {}, what = op) {
  try {
    return await conn.request(op, fields);
  } catch (err) {
    // a fleet's reset is refused while any vehicle is locked: not necessarily the first
    if (err.code === "flight_locked" && (op !== "reset" || !fleet())) setLocked(err.message, fields.vehicle);
    showError(`${what} refused: ${describe(err)}`);
    throw err;
  }
}

// ------------------------------------------------------------------------------------------------ vehicles
const fleet = () => ui.vehicles.length > 1;
const defaultVehicle = () => ui.vehicles[0]?.name ?? "";
const selected = () => ui.selected ?? defaultVehicle();

// A flight op for the selected vehicle (named only in a fleet: one vehicle's requests stay as they were).
function fly(op, fields = {}, what = op) {
  const target = fleet() ? { vehicle: selected() } : {};
  const name = fleet() ? `${what} (${selected()})` : what;
  return send(op, { ...fields, ...target }, name);
}

// The vehicles of a scene_info reply; keeps the selection when the vehicle is still there.
function setVehicles(info) {
  ui.vehicles = info.vehicles ?? [];
  const names = ui.vehicles.map((v) => v.name);
  if (!names.includes(ui.selected)) ui.selected = names[0] ?? null;
  for (const name of Object.keys(ui.states)) if (!names.includes(name)) delete ui.states[name];
  if (ui.vehicles.some((v) => v.controlled_by === "px4")) $("px4").hidden = false;
  map.setVehicles(names, selected());
  buildVehicleList();
  select(selected());
  if (!$("px4").hidden) renderPx4Status();
}

function buildVehicleList() {
  const list = $("vehicle-list");
  list.replaceChildren();
  $("fleet").hidden = !fleet();
  ui.vehicles.forEach((v, i) => {
    const b = document.createElement("button");
    b.dataset.vehicle = v.name;
    b.setAttribute("role", "radio");
    const pilot = { px4: "PX4 SITL", ardupilot: "ArduPilot SITL" }[v.controlled_by] ?? "the simulator";
    b.title = `${v.name}: ${v.params}, flown by ${pilot}`;
    b.innerHTML = `<i style="background: ${FLEET_COLOURS[i % FLEET_COLOURS.length]}"></i><b></b>` +
      `<span class="mode"></span>`;
    b.querySelector("b").textContent = v.name;
    if (v.controlled_by === "px4") b.insertAdjacentHTML("beforeend", `<span class="tag">PX4</span>`);
    if (v.controlled_by === "ardupilot") b.insertAdjacentHTML("beforeend", `<span class="tag">ArduPilot</span>`);
    b.insertAdjacentHTML("beforeend", `<span class="tag locked" hidden>locked</span>`);
    b.insertAdjacentHTML("beforeend", `<span class="tag spray" hidden></span>`);
    b.onclick = () => select(v.name);
    list.append(b);
  });
  renderVehicleList();
}

function renderVehicleList() {
  for (const b of $("vehicle-list").children) {
    const name = b.dataset.vehicle;
    b.setAttribute("aria-checked", String(name === selected()));
    const mode = ui.states[name]?.mode ?? "";
    const span = b.querySelector(".mode");
    if (span.textContent !== mode) span.textContent = mode;
    const lock = b.querySelector(".tag.locked");
    lock.hidden = !ui.locks[name];
    lock.title = ui.locks[name] ?? "";
    const spray = ui.states[name]?.spray;
    const tag = b.querySelector(".tag.spray");
    tag.hidden = !spray;
    const text = spray ? `${spray.on ? "spraying" : "spray off"} · ${litres(spray.level_l)} L` : "";
    if (tag.textContent !== text) tag.textContent = text;
  }
}

// Point the flight controls, the telemetry, the map's highlight and the camera views at `name`.
function select(name) {
  const previous = ui.selected;
  ui.selected = name;
  if (previous !== name && ui.keys.size) {
    ui.keys.clear(); // keys held for the previous vehicle: it holds where it is
    ui.lastVelocity = null;
    send("hold", fleet() ? { vehicle: previous } : {}, "hold").catch(() => {});
  }
  ui.state = ui.states[selected()] ?? null;
  map.select(selected());
  cams.setVehicle(selected(), fleet() ? selected() : null);
  conn.sendUi({ watch: selected() });
  refreshLock();
  renderVehicleList();
  painter.add("telemetry", renderTelemetry);
}

// ------------------------------------------------------------------------------------------------ pages
function showPage(name) {
  $("levels").hidden = name !== "levels";
  $("fly").hidden = name !== "fly";
  $("nav-levels").classList.toggle("active", name === "levels");
  $("nav-fly").classList.toggle("active", name === "fly");
  if (location.hash !== `#${name}`) history.replaceState(null, "", `#${name}`);
  if (name === "levels") loadPreviews();
}

// The scene previews are rendered on demand, one at a time: only once the level select is shown, so a
// page opened on the flight view does not queue its map behind every preview.
function loadPreviews() {
  for (const img of document.querySelectorAll(".card img[data-src]")) {
    img.src = img.dataset.src;
    delete img.dataset.src;
  }
}

async function buildLevels() {
  const res = await fetch(withToken("/api/scenes"));
  const { scenes } = await res.json();
  const cards = $("scene-cards");
  cards.replaceChildren();
  for (const s of scenes) {
    const card = document.createElement("button");
    card.className = "card";
    card.dataset.scene = s.name;
    card.innerHTML = `<img alt="${s.name} preview"><h3></h3><p></p>`;
    card.querySelector("h3").textContent = s.name.replaceAll("_", " ");
    card.querySelector("p").textContent = s.description;
    card.querySelector("img").dataset.src = withToken(`/api/preview/${encodeURIComponent(s.name)}`);
    card.onclick = () => chooseScene(s.name);
    cards.append(card);
  }
  if (!$("levels").hidden) loadPreviews();
}

// The light options of the level select as the `light` field of `reset`: only the fields set ("as now"
// keeps the simulator's), null for a default; null when none is set.
const LIGHT_FIELDS = { "light-time": "time_of_day_h", "light-sky": "cloud_cover", "light-haze": "visibility_m" };
function chosenLight() {
  const light = {};
  for (const [id, field] of Object.entries(LIGHT_FIELDS)) {
    const value = $(id).value;
    if (value !== "") light[field] = value === "null" ? null : Number(value);
  }
  return Object.keys(light).length ? light : null;
}

// One line for the telemetry: "08:00, overcast, visibility 200 m".
function describeLight(l) {
  const h = l.time_of_day_h;
  const two = (n) => String(n).padStart(2, "0");
  const parts = [h === null ? "fixed sun" : `${two(Math.floor(h))}:${two(Math.round((h % 1) * 60))}`];
  if (l.cloud_cover) parts.push(l.cloud_cover >= 1 ? "overcast" : `cloud ${l.cloud_cover}`);
  if (l.visibility_m !== null) parts.push(`visibility ${l.visibility_m} m`);
  return parts.join(", ");
}

async function chooseScene(name) {
  const seed = Number($("seed").value);
  if (!Number.isInteger(seed) || seed < 0) {
    showError(`the seed must be a whole number of 0 or more, not "${$("seed").value}"`);
    return;
  }
  document.body.classList.add("loading");
  try {
    const light = chosenLight();
    const res = await send("reset", { scene: name, seed, ...(light ? { light } : {}) }, `loading ${name}`);
    ui.light = res.light ?? null;
    await loadScene();
    showPage("fly");
  } catch {
    // already shown
  } finally {
    document.body.classList.remove("loading");
  }
}

// Read the scene and its vehicles; `subscribe`: then subscribe to every vehicle's state and events.
async function loadScene(subscribe = false) {
  const info = await send("scene_info", {}, "reading the scene");
  const changed = !ui.scene || ui.scene.name !== info.name || ui.scene.seed !== info.seed;
  ui.scene = info;
  setVehicles(info);
  if (subscribe) {
    const every = info.vehicles ? { vehicle: "*" } : {};
    const streams = { streams: ["state", "events"], rate_hz: STATE_HZ, ...every };
    await send("subscribe", streams, "subscribing to the state");
  }
  document.title = `Droneulator · ${info.name}`;
  if (changed) {
    try {
      await map.load(info.name, info.seed);
    } catch (err) {
      showError(`the map of ${info.name} could not be drawn: ${describe(err)}`);
    }
  }
  $("seed").value = info.seed;
}

// ------------------------------------------------------------------------------------------------ flight
function setLocked(reason, vehicle = defaultVehicle()) {
  if (reason) ui.locks[vehicle] = reason;
  else delete ui.locks[vehicle];
  refreshLock();
  renderVehicleList();
}

function refreshLock() {
  const reason = ui.locks[selected()] ?? null;
  ui.locked = reason;
  $("lock-reason").hidden = !reason;
  const whose = fleet() ? ` of ${selected()}` : "";
  $("lock-reason").textContent = reason ? `Flight controls${whose} are off: ${reason}` : "";
  for (const b of document.querySelectorAll("button.flight")) b.disabled = !!reason;
}

function altitude() {
  const z = Number($("altitude").value);
  return Number.isFinite(z) ? z : 2.0;
}

function mapClicked(x, y, vehicle) {
  if (vehicle && vehicle !== selected()) {
    select(vehicle); // a click on another vehicle selects it
    return;
  }
  if (ui.locked) {
    showError(`not flying there: ${ui.locked}`);
    return;
  }
  const airborne = ui.state && ui.state.mode !== "idle" && ui.state.position[2] > 0.3;
  const z = airborne ? ui.state.position[2] : altitude();
  const target = [round(x), round(y), round(z)];
  const name = selected();
  fly("goto", { position: target }, `flying to (${target[0]}, ${target[1]}, ${target[2]})`).then(
    () => map.setGoal(target, name), () => {});
}

function round(v) {
  return Math.round(v * 100) / 100;
}

function keyVelocity() {
  const speed = Math.min(5, Math.max(0.1, Number($("kspeed").value) || 1.5));
  const k = ui.keys;
  const forward = (k.has("fwd") ? speed : 0) - (k.has("back") ? speed : 0);
  const yawRate = (k.has("left") ? YAW_RATE : 0) - (k.has("right") ? YAW_RATE : 0);
  return [forward, yawRate];
}

function keysChanged() {
  const [forward, yawRate] = keyVelocity();
  const key = `${forward},${yawRate}`;
  if (key === ui.lastVelocity) return;
  ui.lastVelocity = key;
  if (forward === 0 && yawRate === 0) fly("hold", {}, "hold").catch(() => {});
  else {
    map.setGoal(null);
    fly("velocity", { forward, yaw_rate: yawRate }, "keyboard flying").catch(() => {});
  }
}

function typing(e) {
  return ["INPUT", "TEXTAREA", "SELECT"].includes(e.target.tagName);
}

document.addEventListener("keydown", (e) => {
  const k = KEYS[e.code];
  if (!k || typing(e) || $("fly").hidden || ui.locked) return;
  e.preventDefault();
  ui.keys.add(k);
  keysChanged();
});
document.addEventListener("keyup", (e) => {
  const k = KEYS[e.code];
  if (!k || !ui.keys.has(k)) return;
  e.preventDefault();
  ui.keys.delete(k);
  keysChanged();
});
window.addEventListener("blur", () => {
  if (ui.keys.size) {
    ui.keys.clear();
    keysChanged();
  }
});

// ------------------------------------------------------------------------------------------------ telemetry
function onState(state) {
  const name = state.vehicle ?? defaultVehicle();
  const previous = ui.states[name];
  ui.states[name] = state;
  if (previous && state.t < previous.t) {
    map.clearTrail(name); // a reset
    if (name === selected()) ui.rtfSamples = [];
  }
  map.setState(name, state);
  if (state.spray) onSprayState(state);
  if (name !== selected()) return;
  ui.state = state;
  const now = performance.now();
  ui.rtfSamples.push([now, state.t]);
  while (ui.rtfSamples.length > 2 && now - ui.rtfSamples[0][0] > RTF_WINDOW_MS) ui.rtfSamples.shift();
  if (now - ui.telemetryAt >= TELEMETRY_MS) {
    ui.telemetryAt = now;
    painter.add("telemetry", renderTelemetry);
  }
}

// ------------------------------------------------------------------------------------------------ spraying
const litres = (v) => (Number.isFinite(v) ? v.toFixed(2) : "?");

// "on at 100 %, tank 7.42 / 10.00 L" (the spray state of VehicleState.spray)
function describeSpray(sp) {
  const rate = Number.isFinite(sp.rate) ? `${Math.round(sp.rate * 100)} %` : "?";
  return `${sp.on ? `on at ${rate}` : "off"}, tank ${litres(sp.level_l)} / ${litres(sp.tank_l)} L`;
}

// A state with a spray system: show the deposit layer, and ask for the deposit once a second of sim
// time (again at once after a reset: sim time went back), one request at a time; only the newest ask's
// answer is drawn.
function onSprayState(state) {
  if (!ui.spray) {
    ui.spray = true;
    $("deposit-bar").hidden = false;
  }
  const d = ui.deposit;
  if (d.asking && performance.now() - d.askedAt < DEPOSIT_GIVE_UP_MS) return;
  if (d.askedT !== null && state.t >= d.askedT && state.t - d.askedT < DEPOSIT_EVERY_S) return;
  const ask = (d.asking = d.askedAt = performance.now());
  d.askedT = state.t;
  const since = d.version === null ? {} : { since: d.version };
  conn.request("spray_deposit", since)
    .then(async (res) => {
      if (!res || !res.changed) return;
      const layer = await decodeDeposit(res);
      if (ask !== d.asking) return; // given up on: a newer ask is out
      d.version = layer.version;
      d.layer = layer;
      map.setDeposit(layer);
      $("deposit-info").textContent = layer.cells ? `(${layer.cells} cells)` : "(nothing landed yet)";
    })
    .catch((err) => {
      if (err.code === "not_connected" || err.code === "connection_closed") return;
      const text = `the spray deposit could not be drawn: ${describe(err)}`;
      if (d.error !== text) showError(text); // once, not every second
      d.error = text;
    })
    .finally(() => {
      if (ask === d.asking) d.asking = 0;
    });
}

function renderTelemetry() {
  const s = ui.state;
  const rows = [];
  if (fleet()) {
    rows.push(["vehicle", selected()]);
    renderVehicleList();
  }
  if (s && ui.rtfSamples.length) {
    const [x, y, z] = s.position;
    const speed = Math.hypot(...s.velocity);
    const [w0, t0] = ui.rtfSamples[0];
    const [w1, t1] = ui.rtfSamples[ui.rtfSamples.length - 1];
    const rtf = w1 - w0 > 500 ? (t1 - t0) / ((w1 - w0) / 1000) : null;
    rows.push(["mode", s.mode], ["position", `${x.toFixed(2)}, ${y.toFixed(2)}, ${z.toFixed(2)} m`],
      ["speed", `${speed.toFixed(2)} m/s`], ["altitude", `${z.toFixed(2)} m`],
      ["heading", `${((s.yaw * 180) / Math.PI).toFixed(0)}°`], ["sim time", `${s.t.toFixed(2)} s`],
      ["real-time factor", rtf === null ? "…" : rtf.toFixed(2)]);
    if (s.spray && typeof s.spray === "object") rows.push(["spray", describeSpray(s.spray)]);
  }
  if (ui.scene) rows.push(["scene", `${ui.scene.name} (seed ${ui.scene.seed})`]);
  if (ui.light) rows.push(["light", describeLight(ui.light)]);
  const im = ui.images;
  if (im) {
    rows.push(["images shown", `${cams.count}`],
      [`over the ${ui.config.image_hz} Hz cap`, `${Math.max(0, im.received - im.encoded)} skipped`],
      ["frames dropped", `${im.dropped} (page too slow)`]);
  }
  const dl = $("telemetry");
  const shown = [...dl.querySelectorAll("dd")];
  if (shown.length === rows.length && shown.every((dd, i) => dd.dataset.key === rows[i][0])) {
    // same rows: change only the text that changed (no new nodes, no layout of the whole list)
    shown.forEach((dd, i) => {
      if (dd.textContent !== rows[i][1]) dd.textContent = rows[i][1];
    });
    return;
  }
  dl.replaceChildren();
  for (const [k, v] of rows) {
    const dt = document.createElement("dt");
    dt.textContent = k;
    const dd = document.createElement("dd");
    dd.textContent = v;
    dd.dataset.key = k;
    dl.append(dt, dd);
  }
}

function logEvent(ev) {
  const li = document.createElement("li");
  li.className = `event ${ev.type}`;
  const where = ev.position ? ` at (${ev.position.map((v) => v.toFixed(1)).join(", ")})` : "";
  const extra = ev.type === "impact" ? `, ${ev.speed.toFixed(1)} m/s`
    : ev.type === "px4_disconnected" ? `: ${ev.reason}` : "";
  const who = fleet() ? (ev.vehicles ?? [ev.vehicle]).filter(Boolean).join(" & ") : "";
  const prefix = who ? `${who}: ` : "";
  li.textContent = `t=${(ev.t ?? 0).toFixed(2)} s  ${prefix}${ev.type.replaceAll("_", " ")}${where}${extra}`;
  $("events").prepend(li);
  while ($("events").children.length > EVENT_LOG) $("events").lastChild.remove();
}

function onEvent(ev) {
  logEvent(ev);
  const vehicle = ev.vehicle ?? defaultVehicle();
  if (ev.type === "arrived" && ev.command === "goto") map.setGoal(null, vehicle);
  const mine = !fleet() || vehicle === selected() || (ev.vehicles ?? []).includes(selected());
  if ((ev.type === "collision" || ev.type === "impact") && mine) {
    const flash = $("flash");
    flash.classList.remove("on");
    void flash.offsetWidth; // restart the animation
    flash.classList.add("on");
  }
  if (ev.type.startsWith("px4_")) onPx4Event(ev);
}

// PX4's status as the simulator runs it (docs/px4.md): a connected PX4 drives the vehicle, armed or not
// (disarmed: motors off), and flight commands are refused meanwhile. A PX4 lost in the air leaves the
// vehicle to the simulator (px4.on_loss: land, hold or fall); a PX4 that connects over a vehicle in the
// air gets the rotors only once it is on the ground, its arm refused until then. A page opened while PX4
// is already connected learns of it from the API's flight_locked answer to its first command.
const PX4_IN_CONTROL = "PX4 SITL is in control; flight commands come from PX4"; // the runtime's words
const PX4_LOSS = {
  land: "the simulator lands the vehicle clear of the scene",
  hold: "the simulator holds the vehicle where it is",
  fall: "its rotors stopped: the vehicle falls",
  rest: "the vehicle rests on the ground",
};

function onPx4Event(ev) {
  $("px4").hidden = false;
  const vehicle = ev.vehicle ?? defaultVehicle();
  let status = ev.type;
  if (ev.type === "px4_connected") {
    status = ev.holding ? "PX4 connected over a vehicle in the air: the simulator flies it; PX4 gets the rotors once it is on the ground"
      : "PX4 connected and in control (disarmed: motors off)";
    setLocked(ev.holding ? null : PX4_IN_CONTROL, vehicle);
  } else if (ev.type === "px4_armed") {
    status = "PX4 is armed and in control";
    setLocked("PX4 is armed and flying the vehicle", vehicle);
  } else if (ev.type === "px4_disarmed") {
    status = "PX4 disarmed (motors off); still in control until it disconnects";
    setLocked(PX4_IN_CONTROL, vehicle);
  } else if (ev.type === "px4_disconnected") {
    status = `PX4 disconnected (${ev.reason || "no reason given"}): the UI may fly`;
    setLocked(null, vehicle);
  } else if (ev.type === "px4_lost") {
    status = `${ui.px4Status[vehicle] ?? "PX4 lost"}; PX4 was lost: ${PX4_LOSS[ev.action] || ev.action}`;
  } else if (ev.type === "px4_arm_refused") {
    status = "PX4 armed with the vehicle in the air: refused (the simulator flies it until it is on the ground)";
  } else if (ev.type === "px4_in_control") {
    status = "PX4 is in control (it took over on the ground)";
    setLocked(PX4_IN_CONTROL, vehicle);
  }
  ui.px4Status[vehicle] = status;
  renderPx4Status();
}

// One line per PX4 vehicle of a fleet, each named; one vehicle's status alone.
function renderPx4Status() {
  if (!fleet()) {
    $("px4-status").textContent = ui.px4Status[defaultVehicle()] ?? "waiting for PX4…";
    return;
  }
  const px4 = ui.vehicles.filter((v) => v.controlled_by === "px4" || ui.px4Status[v.name]);
  $("px4-status").textContent = px4.map((v) => `${v.name}: ${ui.px4Status[v.name] ?? "waiting for PX4…"}`)
    .join("\n");
}

// ------------------------------------------------------------------------------------------------ connection
function setConnection(text, good) {
  const badge = $("conn");
  badge.textContent = text;
  badge.className = `badge ${good ? "good" : "bad"}`;
}

async function onApiConnected() {
  try {
    await loadScene(true);
    if (ui.scene && location.hash !== "#fly" && !ui.started) showPage("levels");
    ui.started = true;
  } catch {
    // shown already
  }
}

function onUiMessage(msg) {
  if (msg.api) {
    ui.apiConnected = msg.api.connected;
    if (msg.api.connected) {
      setConnection(`simulator: ${msg.api.url}`, true);
      onApiConnected();
    } else {
      setConnection("simulator unreachable, reconnecting…", false);
      showError(`lost the simulator at ${msg.api.url}: ${msg.api.error || "no reason given"}; reconnecting`);
    }
  }
  if (msg.images) {
    ui.images = msg.images;
    // the images' trouble is news only while the simulator is connected: it must not say so when it is not
    if (msg.images.error && ui.apiConnected) setConnection(`simulator connected; ${msg.images.error}`, false);
  }
}

// The UI server asks for its access token (docs/security.md): a small prompt; the token is kept in the
// tab's sessionStorage, then whatever was refused (the connection, the page's set-up) tries again.
// `used` is the token the refused attempt carried (null: none). A refusal that answers an older token
// than the one stored now (its reply came after the user entered another) tries again at once.
const tokenRetries = [];
function askForToken(used, retry) {
  const stored = sessionStorage.getItem(TOKEN_KEY);
  if (stored !== null && stored !== used) {
    retry();
    return;
  }
  setConnection("access token needed", false);
  $("token-why").textContent = used !== null
    ? "That access token was refused. Enter the one printed where the simulator was started."
    : "This simulator asks for its access token (printed where it was started).";
  tokenRetries.push(retry);
  const dialog = $("token-dialog");
  $("token-form").onsubmit = (e) => {
    e.preventDefault();
    const token = $("token-input").value.trim();
    if (!token) return;
    sessionStorage.setItem(TOKEN_KEY, token);
    dialog.close();
    $("token-input").value = "";
    for (const again of tokenRetries.splice(0)) again();
  };
  if (!dialog.open) dialog.showModal();
}

const conn = new Connection({
  onOpen: () => setConnection("waiting for the simulator…", false),
  onClose: () => setConnection("UI server unreachable, reconnecting…", false),
  onUnauthorized: askForToken,
  onImage: (header, bytes) => cams.show(header, bytes),
  onMessage: (msg) => {
    if (msg.type === "state") onState(msg.state);
    else if (msg.type === "event") onEvent(msg.event);
    else if (msg.type === "ui") onUiMessage(msg);
  },
});
ui.conn = conn;

const map = new MapView($("map"), mapClicked);
ui.map = map;
const cams = new CameraViews($("cameras"), { depth_max_m: 20, legend: [] });
ui.cameras = cams;

async function init() {
  const used = sessionStorage.getItem(TOKEN_KEY);
  const res = await fetch(withToken("/api/config"));
  if (res.status === 401) {
    askForToken(used, () => init().catch(startFailed));
    return;
  }
  ui.config = await res.json();
  cams.config = ui.config;
  if (ui.config.px4) $("px4").hidden = false;
  $("deposit-scale").style.background = legendGradient();
  $("deposit-toggle").onchange = (e) => map.setShowDeposit(e.target.checked);
  $("nav-levels").onclick = () => showPage("levels");
  $("nav-fly").onclick = () => showPage("fly");
  const clearGoal = (name) => () => map.setGoal(null, name);
  $("btn-takeoff").onclick = () => fly("takeoff", { altitude: altitude() }, "take off").catch(() => {});
  $("btn-land").onclick = () => fly("land", {}, "land").then(clearGoal(selected()), () => {});
  $("btn-hold").onclick = () => fly("hold", {}, "hold").then(clearGoal(selected()), () => {});
  // a reset restarts the whole world: every vehicle
  $("btn-reset").onclick = () => send("reset", {}, "reset").then(
    () => ui.vehicles.forEach((v) => map.setGoal(null, v.name)), () => {});
  $("btn-alt").onclick = () => {
    if (!ui.state) return;
    const [x, y] = ui.state.position;
    const target = [round(x), round(y), altitude()];
    const name = selected();
    fly("goto", { position: target }, `climbing to ${target[2]} m`).then(
      () => map.setGoal(target, name), () => {});
  };
  $("btn-yaw").onclick = () => {
    if (!ui.state) return;
    const yaw = (Number($("yaw").value) * Math.PI) / 180;
    fly("goto", { position: ui.state.position, yaw }, "turning").catch(() => {});
  };
  showPage(location.hash === "#fly" ? "fly" : "levels");
  await buildLevels();
}

function startFailed(err) {
  showError(`the page could not start: ${describe(err)}`);
}

init().catch(startFailed);
setInterval(() => painter.add("telemetry", renderTelemetry), 1000); // with the next paint
