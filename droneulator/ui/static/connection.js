// The page's one WebSocket to the UI server: the simulator's API protocol (docs/api.md) in text frames,
// camera images in binary frames. Reconnects by itself, every second, whenever the server goes away.
// A server that asks for an access token (docs/security.md) gets it as the `token` query parameter of
// the WebSocket URL (and of every /api/ route: withToken), from the tab's sessionStorage; it closes a
// connection without it with code 1008, and then the page asks for the token (onUnauthorized) instead
// of reconnecting.

export const TOKEN_KEY = "droneulator.token";
const UNAUTHORIZED = 1008;

// `path` (an /api/ route of the UI server) with the tab's access token, when it has one.
export function withToken(path) {
  const token = sessionStorage.getItem(TOKEN_KEY);
  if (!token) return path;
  return `${path}${path.includes("?") ? "&" : "?"}token=${encodeURIComponent(token)}`;
}

export class ApiError extends Error {
  constructor(code, message) {
    super(message);
    this.code = code;
  }
}

export class Connection {
  constructor({ onMessage, onImage, onOpen, onClose, onUnauthorized }) {
    this.handlers = { onMessage, onImage, onOpen, onClose, onUnauthorized };
    this.pending = new Map();
    this.nextId = 1;
    this.ws = null;
    this.open();
  }

  open() {
    const token = sessionStorage.getItem(TOKEN_KEY);
    const query = token ? `?token=${encodeURIComponent(token)}` : "";
    const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws${query}`);
    ws.binaryType = "arraybuffer";
    ws.onopen = () => this.handlers.onOpen();
    ws.onmessage = (e) => this.receive(e.data);
    ws.onclose = (e) => {
      for (const { reject } of this.pending.values()) {
        reject(new ApiError("connection_closed", "the connection to the UI server closed"));
      }
      this.pending.clear();
      this.ws = null;
      if (e.code === UNAUTHORIZED) {
        // ask for the token (again, if the one stored was refused); it is stored, then connect with it
        this.handlers.onUnauthorized(token, () => this.open());
        return;
      }
      this.handlers.onClose();
      setTimeout(() => this.open(), 1000);
    };
    this.ws = ws;
  }

  receive(data) {
    if (data instanceof ArrayBuffer) {
      const view = new DataView(data);
      const n = view.getUint32(0);
      const header = JSON.parse(new TextDecoder().decode(new Uint8Array(data, 4, n)));
      this.handlers.onImage(header, new Uint8Array(data, 4 + n));
      return;
    }
    const msg = JSON.parse(data);
    if ("ok" in msg) {
      const waiter = this.pending.get(msg.id);
      if (!waiter) return;
      this.pending.delete(msg.id);
      if (msg.ok) waiter.resolve(msg.result);
      else waiter.reject(new ApiError(msg.error.code, msg.error.message));
    } else {
      this.handlers.onMessage(msg);
    }
  }

  // A message for the UI server itself ({"type": "ui", ...}); dropped while not connected.
  sendUi(fields) {
    if (this.ws && this.ws.readyState === WebSocket.OPEN) this.ws.send(JSON.stringify({ type: "ui", ...fields }));
  }

  // Send one API request; resolves with its result, rejects with ApiError(code, message).
  request(op, fields = {}) {
    if (!this.ws || this.ws.readyState !== WebSocket.OPEN) {
      return Promise.reject(new ApiError("not_connected", "not connected to the UI server; reconnecting"));
    }
    const id = this.nextId++;
    return new Promise((resolve, reject) => {
      this.pending.set(id, { resolve, reject });
      this.ws.send(JSON.stringify({ id, op, ...fields }));
    });
  }
}
