// TACF ground station page. Plain JavaScript, no library, no network access beyond this dashboard's own server:
// - one EventSource on /events brings every session's newest box, health and chart points (latest-only, capped);
// - one frame feed per session card, and one for the "New session" panel, poll /frame/<key> with at most one
//   request in flight and at most FRAME_HZ, so a slow browser simply shows fewer frames;
// - charts are drawn on <canvas> by hand (drawChart).
// window.tacf exposes the page's state for end-to-end tests.
"use strict";

const FRAME_HZ = 10;
const FRAME_BACKOFF_MAX_MS = 5000;   // the slowest poll of a feed that keeps failing (no frames, dashboard down)
const STALE_MS = 4000;               // health comes about once a second: silent this long, a session is shown stale
const STATUS_MS = 10000;             // how long "session X started" stays
const BOX_HISTORY = 64;    // boxes kept per session: a frame poll lags the boxes by a few of them at most
const BOX_FRESH_MS = 1500;           // a box older than this is drawn only on its own frame, not on newer ones
const CHART_REDRAW_MS = 1000;
const RECONNECT_MS = 2000;           // as the retry the event stream asks of the browser's own reconnections
const COLOURS = { ok: "#00e676", lost: "#ff5252", draft: "#ffca28", pme: "#4fc3f7", fps: "#ffb74d",
                  grid: "#2c3644", text: "#8a96a8" };

const state = {
  sessions: new Map(),     // id -> session JSON (see SessionView.to_json)
  points: new Map(),       // id -> [{t, fps, pme, proc, age}]
  boxes: new Map(),        // id -> Map(frame seq -> box): the last BOX_HISTORY boxes, to draw a frame's own box
  keys: [],                // watched image keys
  nodes: {},               // node -> max_sessions
  historyMs: 300000,
  feeds: new Map(),        // "<image key>#<session id>" -> the FrameFeed of that session's card
  newFeed: null,           // the FrameFeed of the "New session" panel: it follows the selected key
  chosenKey: null,         // the key the operator last chose for that panel (typed in the watch box, or selected)
  cards: new Map(),        // id -> card elements
  drawn: {},               // id -> what the last frame draw showed (tests read it)
  charts: {},              // id -> {points, redraws, labels, last} of the last chart draw (tests read it)
  reinit: null,            // id of the session being re-initialised by drawing
  clockOffsetMs: 0,        // server clock - this browser's clock (chart times are when the dashboard got the health)
  events: 0,
  connected: false,
};
window.tacf = state;

// ------------------------------------------------------------------------------------------------ helpers
const $ = (sel, root = document) => root.querySelector(sel);
const serverNow = () => Date.now() + state.clockOffsetMs;
const fmt = (v, digits = 1) => (v === null || v === undefined || Number.isNaN(v)) ? "–" : Number(v).toFixed(digits);

function toast(message) {
  const el = $("#toast");
  el.textContent = message;
  el.hidden = false;
  clearTimeout(toast.timer);
  toast.timer = setTimeout(() => { el.hidden = true; }, 6000);
}

// Frame seqs are 64-bit counts (a camera may count nanoseconds), past the 2^53 that a JS Number holds exactly: the
// page keeps them as BigInt, read from and written to JSON as plain numbers. In JSON text a field name is followed
// by its colon only outside strings (inside one its quotes are escaped), so quoting the seq fields' digits is safe.
const SEQ_FIELDS = /"(seq|init_seq|last_seq)":\s*(\d+)/g, SEQ_NAMES = new Set(["seq", "init_seq", "last_seq"]);
const BIGINT_MARK = "@tacf-bigint:";

function parseJSON(text) {
  return JSON.parse(text.replace(SEQ_FIELDS, '"$1":"$2"'),
                    (key, v) => SEQ_NAMES.has(key) && typeof v === "string" ? BigInt(v) : v);
}

function toJSON(value) {
  return String(JSON.stringify(value, (key, v) => typeof v === "bigint" ? BIGINT_MARK + v : v))   // undefined too
    .replace(new RegExp(`"${BIGINT_MARK}(\\d+)"`, "g"), "$1");
}

async function post(path, body) {
  const response = await fetch(path, { method: "POST", headers: { "Content-Type": "application/json" },
                                       body: toJSON(body) });
  const data = await response.text().then(parseJSON).catch(() => ({}));
  if (!response.ok) throw new Error(`${data.error || response.status}: ${data.message || response.statusText}`);
  return data;
}

// ------------------------------------------------------------------------------------------------ frames
class FrameFeed {
  // The newest frame of one image key (none: idle until setKey): polls /frame/<key> (ETag: 304 when nothing new),
  // one request at a time, until stop(). A poll that fails (a key without frames, the dashboard restarting) makes
  // the next one wait twice as long, up to FRAME_BACKOFF_MAX_MS: on a thin link every poll counts.
  // seqOf(): a frame seq to show instead of the newest (the frame a session's box was computed on), or null.
  constructor(key, seqOf = () => null) {
    this.seqOf = seqOf; this.frames = 0; this.failures = 0; this.stopped = false; this.wake = null;
    this.setKey(key);
    this.loop();
  }
  setKey(key) {
    if (key === this.key) return;
    this.key = key; this.bitmap = null; this.seq = null; this.width = 0; this.height = 0; this.etag = null;
    this.failures = 0; this.error = null;
    if (this.wake) this.wake();
  }
  stop() {
    this.stopped = true;
    if (this.wake) this.wake();
  }
  async loop() {
    while (!this.stopped) {
      const started = performance.now(), key = this.key;
      let ok = false;
      if (key) {
        try {
          const headers = this.etag ? { "If-None-Match": this.etag } : {};
          const seq = this.seqOf();
          const url = "/frame/" + encodeURI(key) + (seq === null || seq === undefined ? "" : `?seq=${seq}`);
          const response = await fetch(url, { headers, cache: "no-store" });
          ok = response.status === 200 || response.status === 304;
          // why not (a camera whose frames are no images, a key not watched): shown, over the last frame if any;
          // a reply that is no JSON of ours (a reverse proxy's 502 or 504 page) is said by its status
          const error = ok ? null : await response.json().then((body) => body.message).catch(() => null)
                                    || `frame request failed: HTTP ${response.status}`;
          if (key === this.key && error !== this.error) { this.error = error; scheduleDraw(); }
          if (response.status === 200) {
            const bitmap = await createImageBitmap(await response.blob());
            if (key === this.key) {                 // else the key changed meanwhile: not this feed's frame
              // no bitmap.close(): a drawing in progress may still hold the previous frame
              this.bitmap = bitmap;
              this.etag = response.headers.get("ETag");
              this.seq = BigInt(response.headers.get("X-Seq"));
              this.width = bitmap.width; this.height = bitmap.height;
              this.frames += 1;
              scheduleDraw();
            }
          }
        } catch (err) { ok = false; /* server restarting or frame not decodable: try again */ }
        if (key === this.key) this.failures = ok ? 0 : this.failures + 1;
      }
      const backoff = this.failures ? Math.min(FRAME_BACKOFF_MAX_MS, (1000 / FRAME_HZ) * 2 ** this.failures) : 0;
      const wait = Math.max(1000 / FRAME_HZ - (performance.now() - started), backoff, document.hidden ? 1000 : 0);
      await new Promise((resolve) => { this.wake = resolve; if (key) setTimeout(resolve, wait); });
    }
  }
}

// A session's card shows the frame its newest box was computed on (so box and picture match), or the newest
// frame when boxes stopped coming.
function sessionFeed(id) {
  const session = state.sessions.get(id);
  if (!session || !session.image_key) return null;
  const name = `${session.image_key}#${id}`;
  let feed = state.feeds.get(name);
  if (!feed || feed.key !== session.image_key) {
    if (feed) feed.stop();
    feed = new FrameFeed(session.image_key, () => {
      const s = state.sessions.get(id);
      return s && s.box && boxIsFresh(s) ? s.box.seq : null;
    });
    state.feeds.set(name, feed);
  }
  return feed;
}

function boxIsFresh(session) {
  return Date.now() - (session.boxAt || 0) < BOX_FRESH_MS;
}

// Canvas pixels are image pixels: the canvas is resized to the frame, CSS scales it to the card.
function paintFrame(canvas, feed) {
  const ctx = canvas.getContext("2d");
  if (!feed || !feed.bitmap) {
    ctx.fillStyle = "#000"; ctx.fillRect(0, 0, canvas.width, canvas.height);
    ctx.fillStyle = COLOURS.text; ctx.font = "16px sans-serif";
    ctx.fillText(feed && feed.key ? feed.error || `waiting for frames on ${feed.key}` : "no image key", 16, 28,
                 canvas.width - 32);
    return false;
  }
  if (canvas.width !== feed.width || canvas.height !== feed.height) {
    canvas.width = feed.width; canvas.height = feed.height;
  }
  ctx.drawImage(feed.bitmap, 0, 0);
  return true;
}

// Why the frames stopped (undecodable, or the request failed), on a banner across the top of the last good one,
// which must not pass for live: drawn last, so that a box's label near the top edge does not cover it.
function paintFrameError(canvas, feed) {
  if (!feed.error) return;
  const ctx = canvas.getContext("2d");
  const k = canvas.width / (canvas.clientWidth || canvas.width), size = 12 * k;   // as strokeBox's
  ctx.fillStyle = "rgba(0,0,0,0.75)"; ctx.fillRect(0, 0, canvas.width, size * 1.8);
  ctx.fillStyle = COLOURS.lost; ctx.font = `bold ${size}px sans-serif`;
  ctx.fillText(feed.error, 4 * k, size * 1.3, canvas.width - 8 * k);
}

function strokeBox(ctx, box, colour, label, dashed = false) {
  // Sizes in screen pixels: the canvas holds image pixels and CSS scales it.
  const [x, y, w, h] = box;
  const k = ctx.canvas.width / (ctx.canvas.clientWidth || ctx.canvas.width);
  ctx.save();
  ctx.lineWidth = Math.max(2, 2.5 * k); ctx.strokeStyle = colour;
  if (dashed) ctx.setLineDash([8 * k, 5 * k]);
  ctx.strokeRect(x, y, w, h);
  if (label) {
    const size = 12 * k;
    ctx.font = `bold ${size}px sans-serif`;
    const width = ctx.measureText(label).width + 6 * k;
    const top = y >= size * 1.5 ? y - size * 1.5 : y + h + 2 * k;
    ctx.fillStyle = "rgba(0,0,0,0.6)"; ctx.fillRect(x - ctx.lineWidth / 2, top, width, size * 1.35);
    ctx.fillStyle = colour; ctx.fillText(label, x + 2 * k, top + size * 1.05);
  }
  ctx.restore();
}

// ------------------------------------------------------------------------------------------------ drawing a box
const drafts = new WeakMap();   // canvas -> {x0, y0, x1, y1, the feed's bitmap, seq and key at mouse-down}

function canvasPoint(canvas, event) {
  const rect = canvas.getBoundingClientRect();
  return [(event.clientX - rect.left) * canvas.width / rect.width,
          (event.clientY - rect.top) * canvas.height / rect.height];
}

function enableDrawing(canvas, feedOf, onBox) {
  const begin = (point) => {       // a mouse event or a Touch: true if a draft starts
    const feed = feedOf();
    if (!feed || !feed.bitmap || !canvas.classList.contains("drawable")) return false;
    const [x, y] = canvasPoint(canvas, point);
    // Hold the frame the operator draws on: the box is sent with its seq and key (the key list may change
    // during the drag, and the selected key with it).
    drafts.set(canvas, { x0: x, y0: y, x1: x, y1: y, bitmap: feed.bitmap, seq: feed.seq, key: feed.key });
    return true;
  };
  const move = (point) => {
    const draft = drafts.get(canvas);
    if (!draft) return false;
    [draft.x1, draft.y1] = canvasPoint(canvas, point);
    scheduleDraw();
    return true;
  };
  canvas.addEventListener("mousedown", (event) => { if (event.button === 0 && begin(event)) event.preventDefault(); });
  canvas.addEventListener("mousemove", move);
  const finish = (event) => {
    const draft = drafts.get(canvas);
    if (!draft) return;
    drafts.delete(canvas);
    [draft.x1, draft.y1] = canvasPoint(canvas, event);
    const clamp = (v, max) => Math.min(Math.max(v, 0), max);
    const x0 = clamp(Math.min(draft.x0, draft.x1), canvas.width), x1 = clamp(Math.max(draft.x0, draft.x1), canvas.width);
    const y0 = clamp(Math.min(draft.y0, draft.y1), canvas.height), y1 = clamp(Math.max(draft.y0, draft.y1), canvas.height);
    scheduleDraw();
    if (x1 - x0 < 4 || y1 - y0 < 4) return;          // a click, not a box
    onBox([Math.round(x0), Math.round(y0), Math.round(x1 - x0), Math.round(y1 - y0)], draft.seq, draft.key);
  };
  canvas.addEventListener("mouseup", finish);
  // Leaving the canvas ends the drag where the mouse went out (clamped to the edge): a box dragged past the frame's
  // edge reaches it, not the last move inside, which can be far from it in a quick drag.
  canvas.addEventListener("mouseleave", finish);
  // A finger draws too (a tablet at the ground station): a touch that moves fires no mouse event at all, and
  // would scroll the page. A second finger (a pinch) drops the draft.
  canvas.addEventListener("touchstart", (event) => {
    if (event.touches.length === 1 ? begin(event.touches[0]) : drafts.delete(canvas)) event.preventDefault();
  }, { passive: false });
  canvas.addEventListener("touchmove", (event) => { if (move(event.changedTouches[0])) event.preventDefault(); },
                          { passive: false });
  canvas.addEventListener("touchend", (event) => finish(event.changedTouches[0]));
  canvas.addEventListener("touchcancel", () => { drafts.delete(canvas); scheduleDraw(); });
}

function paintDraft(canvas) {
  const draft = drafts.get(canvas);
  if (!draft) return false;
  canvas.getContext("2d").drawImage(draft.bitmap, 0, 0);
  const x = Math.min(draft.x0, draft.x1), y = Math.min(draft.y0, draft.y1);
  strokeBox(canvas.getContext("2d"), [x, y, Math.abs(draft.x1 - draft.x0), Math.abs(draft.y1 - draft.y0)],
            COLOURS.draft, "new box", true);
  return true;
}

// ------------------------------------------------------------------------------------------------ charts
function drawChart(canvas, points, field, colour, now) {
  const dpr = window.devicePixelRatio || 1;
  const cssW = canvas.clientWidth || 300, cssH = canvas.clientHeight || 110;
  const width = Math.round(cssW * dpr), height = Math.round(cssH * dpr);
  if (canvas.width !== width || canvas.height !== height) { canvas.width = width; canvas.height = height; }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, cssW, cssH);
  const left = 34, right = 6, top = 6, bottom = 16;
  const w = cssW - left - right, h = cssH - top - bottom;
  // The window grows with the data, a minute at a time, up to the history the dashboard keeps.
  const span = points.length ? now - points[0].t : 0;
  const windowMs = Math.min(state.historyMs, Math.max(60000, Math.ceil(span / 60000) * 60000));
  const t0 = now - windowMs;
  const values = points.filter((p) => p.t >= t0 && p[field] !== null && p[field] !== undefined);
  let max = Math.max(1, ...values.map((p) => p[field]));
  const magnitude = Math.pow(10, Math.floor(Math.log10(max)));
  max = Math.ceil(max * 1.1 / magnitude) * magnitude;
  ctx.font = "10px sans-serif"; ctx.fillStyle = COLOURS.text; ctx.strokeStyle = COLOURS.grid; ctx.lineWidth = 1;
  for (let i = 0; i <= 2; i++) {                                   // horizontal grid: 0, max/2, max
    const y = top + h - (h * i) / 2;
    ctx.beginPath(); ctx.moveTo(left, y); ctx.lineTo(left + w, y); ctx.stroke();
    ctx.fillText(fmt((max * i) / 2, max >= 10 ? 0 : 1), 2, y + 3);
  }
  const tickMs = windowMs <= 60000 ? 10000 : 60000;                // ticks back from now: 10 s or 1 min
  const labels = [];
  for (let k = 0; k * tickMs <= windowMs; k++) {
    const x = left + w * (1 - (k * tickMs) / windowMs);
    ctx.beginPath(); ctx.moveTo(x, top + h); ctx.lineTo(x, top + h + 3); ctx.stroke();
    const text = k === 0 ? "now" : tickMs < 60000 ? `-${k * 10}s` : `-${k}m`;
    const lx = Math.min(x - 8, left + w - 18), lw = ctx.measureText(text).width;
    if (labels.length && lx + lw + 3 > labels[labels.length - 1].x) continue;   // a narrow chart: it would touch
    ctx.fillText(text, lx, cssH - 3);
    labels.push({ text, x: lx, w: lw });
  }
  if (values.length) {
    ctx.strokeStyle = colour; ctx.lineWidth = 1.5; ctx.beginPath();
    values.forEach((p, i) => {
      const x = left + (w * (p.t - t0)) / windowMs, y = top + h - (h * p[field]) / max;
      if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y);
    });
    ctx.stroke();
    const last = values[values.length - 1];
    ctx.fillStyle = colour; ctx.font = "bold 12px sans-serif";
    ctx.fillText(fmt(last[field]), left + w - 40, top + 12);
  }
  return labels;
}

// ------------------------------------------------------------------------------------------------ session cards
function cardFor(session) {
  let card = state.cards.get(session.id);
  if (card) return card;
  const root = $("#card-template").content.firstElementChild.cloneNode(true);
  root.dataset.id = session.id;
  root.id = "card-" + session.id.replace(/[^A-Za-z0-9_-]/g, "_");
  card = { root, frame: $("canvas.frame", root), pme: $("canvas.pme", root), fps: $("canvas.fps", root),
           badge: $(".state", root) };
  $(".sid", root).textContent = session.sid;
  $(".node", root).textContent = "on " + session.node;
  // the card's id is node/sid: its session's sid and node never change, even if it goes while a box is drawn
  enableDrawing(card.frame, () => sessionFeed(session.id), async (box, seq) => {
    setReinit(null);
    try {
      await post("/api/reinit", { sid: session.sid, node: session.node, box, seq });
    } catch (err) { toast(`re-init ${session.sid}: ${err.message}`); }
  });
  state.cards.set(session.id, card);
  $("#cards").appendChild(root);
  return card;
}

function setReinit(id) {
  state.reinit = id;
  for (const [cid, card] of state.cards) {
    const on = cid === id;
    card.root.classList.toggle("reinit", on);
    card.frame.classList.toggle("drawable", on);
    $(".reinit-hint", card.root).hidden = !on;
    // a box being drawn on a card no longer re-initialising is dropped: Esc in mid-drag cancels, as the hint says
    if (!on && drafts.delete(card.frame)) scheduleDraw();
  }
}
document.addEventListener("keydown", (event) => { if (event.key === "Escape") setReinit(null); });

function paintCard(id) {
  const session = state.sessions.get(id), card = state.cards.get(id);
  if (!session || !card) return;
  if (paintDraft(card.frame)) return;
  const feed = sessionFeed(id);
  if (!paintFrame(card.frame, feed)) return;
  // Boxes arrive faster than frames are polled: draw the box computed on the frame shown, if it is known, else
  // the newest if it is fresh; an old one (the service hung, frames going on) would sit green on a moving target.
  // After a start or re-init from a dashboard, the box it gave until the tracker's first box on a later frame.
  const box = state.boxes.get(id)?.get(feed.seq) || (session.box && boxIsFresh(session) ? session.box : null);
  const init = !box && session.init && feed.seq >= session.init.seq ? session.init : null;
  if (box || init) {
    const colour = init ? COLOURS.draft : box.ok ? COLOURS.ok : COLOURS.lost;
    strokeBox(card.frame.getContext("2d"), init ? init.box : box.box, colour,
              init ? `${session.sid}  initial box` : `${session.sid}  PME ${fmt(box.pme)}${box.ok ? "" : "  LOST"}`);
    const drawn = state.drawn[id] || { count: 0 };
    state.drawn[id] = { count: drawn.count + 1, box: init ? init.box : box.box, boxSeq: init ? init.seq : box.seq,
                        frameSeq: feed.seq, colour };
  }
  paintFrameError(card.frame, feed);
}

function paintCharts(now) {
  for (const [id, card] of state.cards) {
    const points = state.points.get(id) || [];
    const labels = drawChart(card.pme, points, "pme", COLOURS.pme, now);
    drawChart(card.fps, points, "fps", COLOURS.fps, now);
    const chart = state.charts[id] || { redraws: 0 };
    state.charts[id] = { points: points.length, redraws: chart.redraws + 1, labels,
                         last: points.length ? points[points.length - 1] : null };
  }
}

// ------------------------------------------------------------------------------------------------ session table
// Rows are kept and updated in place (never rebuilt), so that a click on a button is never lost to a refresh.
const rowsById = new Map();

function makeRow(s) {
  const tr = document.createElement("tr");
  tr.dataset.id = s.id; tr.dataset.sid = s.sid;
  for (let i = 0; i < 10; i++) tr.appendChild(document.createElement("td"));
  const badge = document.createElement("span");
  tr.cells[3].appendChild(badge); tr.cells[3].className = "state";
  for (let i = 4; i < 10; i++) tr.cells[i].className = "num";
  const actions = document.createElement("td");
  const reinit = document.createElement("button");
  reinit.textContent = "re-init"; reinit.className = "reinit";
  reinit.title = "draw a new box on this session's frame";
  reinit.onclick = () => {
    setReinit(state.reinit === s.id ? null : s.id);
    state.cards.get(s.id)?.root.scrollIntoView({ block: "nearest" });
  };
  const stop = document.createElement("button");
  stop.textContent = "stop"; stop.className = "stop danger";
  stop.onclick = async () => {
    // A session stopped and started again under its id (by another client) before the next event keeps this row:
    // the reply must neither take the new one off the page nor leave its stop button disabled.
    const generation = state.sessions.get(s.id)?.generation;
    stop.disabled = true;
    try {
      await post("/api/stop", { sid: s.sid, node: s.node });
      const now = state.sessions.get(s.id);
      if (!now || now.generation === generation) { removeSession(s.id); clearNewStatus(s.sid); renderTable(); }
    } catch (err) { toast(`stop ${s.sid}: ${err.message}`); }
    stop.disabled = false;
  };
  actions.append(reinit, " ", stop);
  tr.appendChild(actions);
  return tr;
}

function renderTable() {
  const body = $("#sessions tbody");
  const rows = [...state.sessions.values()].sort((a, b) => a.id.localeCompare(b.id));
  $("#no-sessions").hidden = rows.length > 0;
  for (const [id, tr] of rowsById) if (!state.sessions.has(id)) { tr.remove(); rowsById.delete(id); }
  rows.forEach((s, index) => {
    let tr = rowsById.get(s.id);
    if (!tr) { tr = makeRow(s); rowsById.set(s.id, tr); }
    if (body.children[index] !== tr) body.insertBefore(tr, body.children[index] || null);
    const h = s.health || {};
    const texts = [s.sid, s.node, s.image_key || "–", null, fmt(h.fps), fmt(s.box ? s.box.pme : h.pme),
                   h.frame_age_ms == null ? "–" : `${fmt(h.frame_age_ms, 0)} ms`,
                   s.box && s.box.latency_ms != null ? `${fmt(s.box.latency_ms, 0)} ms` : "–",
                   h.frames_lost == null ? "–" : String(h.frames_lost),
                   h.frames_dropped == null ? "–" : String(h.frames_dropped)];
    texts.forEach((text, i) => { if (text !== null && tr.cells[i].textContent !== text) tr.cells[i].textContent = text; });
    setBadge(tr.cells[3].firstChild, s);
    const card = state.cards.get(s.id);
    if (card) setBadge(card.badge, s);
  });
  const nodes = Object.entries(state.nodes);
  $("#services").textContent = nodes.length
    ? "services: " + nodes.map(([node, max]) => `${node} (${rows.filter((s) => s.node === node).length}/${max})`).join(", ")
    : "no service answered";
}

// The service's state for the session, unless the session's health stopped coming (its service hung or silent:
// the dashboard keeps such a session until its service's token goes, or 30 s without news while the token stays)
// or says the camera stopped (a still frame looks tracked).
function setBadge(el, s) {
  const h = s.health || {};
  const silentS = s.healthAt === null ? 0 : Math.round((Date.now() - s.healthAt) / 1000);
  let shown = s.state, text = s.state;
  if (silentS * 1000 > STALE_MS) {
    shown = "stale"; text = `no news for ${silentS} s`;
  } else if ((s.state === "tracking" || s.state === "lost") && (h.message || "").startsWith("waiting for frames")) {
    shown = "noframes"; text = "no frames";
  }
  const className = `badge state-${shown}`, title = h.message || "";
  if (el.className !== className) el.className = className;
  if (el.textContent !== text) el.textContent = text;
  if (el.title !== title) el.title = title;
}

function renderKeys() {
  const select = $("#key-select");
  const current = select.value;
  const keys = [...state.keys];
  if (keys.join("\n") === [...select.options].map((o) => o.value).join("\n")) return;
  select.replaceChildren(...keys.map((k) => { const o = document.createElement("option"); o.value = o.textContent = k; return o; }));
  if (keys.includes(current)) select.value = current;
  followSelectedKey();
}

// The services a new session may go to: "least loaded" (the value "") first, so that a start needs no choice
// when a second service comes up; a chosen service that goes falls back to it.
function renderNodes() {
  const select = $("#node-select");
  const nodes = ["", ...Object.keys(state.nodes).sort()];
  if (nodes.join("\n") === [...select.options].map((o) => o.value).join("\n")) return;
  const current = select.value;
  select.replaceChildren(...nodes.map((n) => {
    const o = document.createElement("option"); o.value = n; o.textContent = n || "least loaded"; return o;
  }));
  select.value = nodes.includes(current) ? current : "";
}

function followSelectedKey() {
  state.newFeed.setKey($("#key-select").value || null);
  scheduleDraw();
}

// ------------------------------------------------------------------------------------------------ state updates
function mergeSessions(sessions) {
  for (const s of sessions) {
    const old = state.sessions.get(s.id);
    s.boxAt = s.box && old && old.box && old.box.seq === s.box.seq ? old.boxAt
            : s.box ? Date.now() - (s.box.age_ms || 0) : 0;
    s.healthAt = s.health && s.health.received_age_ms != null ? Date.now() - s.health.received_age_ms : null;
    // a new start or re-init: the boxes remembered are the tracker's from before it
    if (s.init && toJSON(s.init) !== toJSON(old && old.init)) state.boxes.delete(s.id);
    state.sessions.set(s.id, s);
    if (s.box) rememberBox(s.id, s.box);
    cardFor(s);
  }
}

function rememberBox(id, box) {
  let boxes = state.boxes.get(id);
  if (!boxes) { boxes = new Map(); state.boxes.set(id, boxes); }
  boxes.set(box.seq, box);
  if (boxes.size > BOX_HISTORY) boxes.delete(boxes.keys().next().value);   // Maps iterate oldest first
}

function mergePoints(points) {
  for (const [id, list] of Object.entries(points || {})) {
    const mine = state.points.get(id) || [];
    const lastT = mine.length ? mine[mine.length - 1].t : -Infinity;
    for (const p of list) if (p.t > lastT) mine.push(p);            // a reconnect may resend points
    const horizon = serverNow() - state.historyMs - 60000;
    while (mine.length && mine[0].t < horizon) mine.shift();
    state.points.set(id, mine);
  }
}

function removeSession(id) {
  const session = state.sessions.get(id);
  if (session && state.feeds.has(`${session.image_key}#${id}`)) {
    state.feeds.get(`${session.image_key}#${id}`).stop();
    state.feeds.delete(`${session.image_key}#${id}`);
  }
  state.sessions.delete(id); state.points.delete(id); state.boxes.delete(id);
  delete state.drawn[id]; delete state.charts[id];     // else one more for each session the open page ever showed
  const card = state.cards.get(id);
  if (card) { card.root.remove(); state.cards.delete(id); }
  if (state.reinit === id) setReinit(null);
}

function applyState(data) {
  const reinit = state.reinit, selected = $("#key-select").value;
  for (const id of [...state.sessions.keys()]) removeSession(id);
  state.historyMs = (data.history_s || 300) * 1000;
  mergeSessions(data.sessions);
  mergePoints(data.points);
  state.keys = data.keys; state.nodes = data.nodes || {};
  // every (re)connection of the event stream starts with this: a re-init the operator chose stays on its new card
  if (state.cards.has(reinit)) setReinit(reinit);
  refresh();
  // A restarted dashboard knows only its --key keys and its sessions' ones: the key the operator typed and still
  // had selected is asked for again, once (a refusal is said and the panel goes on without it).
  if (selected && selected === state.chosenKey && !data.keys.includes(selected)) {
    watchKey(selected).then((ok) => { if (ok && state.chosenKey === selected) selectKey(selected); });
  }
}

function applyUpdate(data) {
  (data.removed || []).forEach(removeSession);     // first: a session replaced by one with the same id is in both
  mergeSessions(data.sessions);
  mergePoints(data.points);
  state.keys = data.keys; state.nodes = data.nodes || state.nodes;
  refresh(Object.keys(data.points || {}).length > 0);
}

function refresh(newPoints = true) {
  renderTable(); renderKeys(); renderNodes(); scheduleDraw();
  if (newPoints) paintCharts(serverNow());
}

// ------------------------------------------------------------------------------------------------ the loop
let drawQueued = false;
function scheduleDraw() {
  if (drawQueued) return;
  drawQueued = true;
  requestAnimationFrame(() => {
    drawQueued = false;
    for (const id of state.cards.keys()) paintCard(id);
    const canvas = $("#new-canvas");
    if (!paintDraft(canvas) && paintFrame(canvas, state.newFeed)) paintFrameError(canvas, state.newFeed);
  });
}
setInterval(() => { paintCharts(serverNow()); renderTable(); }, CHART_REDRAW_MS);   // time passes without news too

function connect() {
  const source = new EventSource("/events");
  const conn = $("#conn");
  source.addEventListener("open", () => { state.connected = true; conn.textContent = "live"; conn.className = "conn up"; });
  source.addEventListener("error", async () => {
    state.connected = false; conn.textContent = "reconnecting…"; conn.className = "conn down";
    // A reply other than the stream (a reverse proxy's 502 while the dashboard restarts behind it) ends an
    // EventSource for good, where a lost connection only has it retry: then a new one (read before the probe)
    const ended = source.readyState === EventSource.CLOSED;
    // EventSource hides the status: ask once, so that a lost token (a restarted dashboard) says what to do
    const probe = await fetch("/api/state").catch(() => null);
    if (probe && probe.status === 401) {
      source.close();
      conn.textContent = "signed out: open the address tacf dashboard printed";
    } else if (ended) {
      setTimeout(connect, RECONNECT_MS);
    }
  });
  const received = (handler) => (e) => {
    const data = parseJSON(e.data);
    state.events += 1; state.clockOffsetMs = data.t - Date.now();
    handler(data);
  };
  source.addEventListener("state", received(applyState));
  source.addEventListener("update", received(applyUpdate));
}

// ------------------------------------------------------------------------------------------------ new session panel
async function watchKey(key) {     // true once the dashboard watches it; a refusal is said
  try {
    const reply = await post("/api/watch", { key });
    state.keys = reply.keys; renderKeys();
    return true;
  } catch (err) { toast(`watch ${key}: ${err.message}`); return false; }
}

function selectKey(key) {
  $("#key-select").value = key; state.chosenKey = key;
  followSelectedKey();
}

$("#watch-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  const key = $("#key-input").value.trim();
  if (key && await watchKey(key)) { selectKey(key); $("#key-input").value = ""; }
});
$("#key-select").addEventListener("change", () => selectKey($("#key-select").value));
state.newFeed = new FrameFeed(null);

function setNewStatus(text, sid = null) {
  const status = $("#new-status");
  status.textContent = text; status.dataset.sid = sid || "";
  clearTimeout(setNewStatus.timer);
  if (sid) setNewStatus.timer = setTimeout(() => clearNewStatus(sid), STATUS_MS);
}

function clearNewStatus(sid) {      // "session X started" is news for a while, and wrong once X is stopped
  if ($("#new-status").dataset.sid === sid) setNewStatus("");
}

enableDrawing($("#new-canvas"), () => state.newFeed, async (box, seq, key) => {
  const sid = $("#sid-input").value.trim(), node = $("#node-select").value;
  setNewStatus(`starting a session on ${key} at (${box.join(", ")}) of frame ${seq}…`);
  try {
    const info = await post("/api/start", { image_key: key, box, seq, sid: sid || undefined,
                                                 node: node || undefined });
    setNewStatus(`session ${info.sid} started on ${info.node} (${info.state})`, info.sid);
    $("#sid-input").value = "";
  } catch (err) { setNewStatus(`start failed: ${err.message}`); toast(`start: ${err.message}`); }
});

connect();
