// The gateway's page: live values, sensor care, a device's register map, bus health, guided
// calibration, a scan of an idle line, the records and a grab-sample verification at the basin.
// Hand-written, no build step; data is always put in the page
// as text (textContent), never as HTML.
"use strict";

const view = document.getElementById("view");
const connection = document.getElementById("connection");
let session = { signed_in: false, csrf: null, who: null, role: null, can_write: false, can_sign_in: false, can_read: true };
let latest = null; // the last overview from the event stream
let onState = null; // the current page's listener of new overviews
let timer = null; // the current page's polling timer
const history = new Map(); // "device/point" -> recent numbers, to see a reading settle

// --- little helpers ---------------------------------------------------------------------

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value === null || value === undefined || value === false) continue;
    if (key === "class") node.className = value;
    else if (key === "text") node.textContent = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value === true ? "" : String(value));
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

async function api(method, path, body) {
  const headers = { Accept: "application/json" };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  if (method !== "GET" && session.csrf) headers["X-CSRF-Token"] = session.csrf;
  const response = await fetch(path, {
    method,
    headers,
    body: body === undefined ? undefined : JSON.stringify(body),
    credentials: "same-origin",
  });
  let data = null;
  try { data = await response.json(); } catch { data = null; }
  if (!response.ok) {
    const error = new Error((data && data.error) || `${response.status} ${response.statusText}`);
    error.status = response.status;
    throw error;
  }
  return data;
}

function show(...nodes) {
  view.replaceChildren(...nodes.filter((node) => node !== null && node !== undefined && node !== ""));
}

function numeric(text) {
  return text !== "" && !Number.isNaN(Number(text));
}

function quality(value) {
  return value ? value.quality : "none";
}

function onlineBadge(online) {
  if (online === true) return el("span", { class: "badge online", text: "online" });
  if (online === false) return el("span", { class: "badge offline", text: "offline" });
  return el("span", { class: "badge unknown", text: "not heard yet" });
}

function ago(seconds) {
  if (seconds === null || seconds === undefined) return "never";
  if (seconds < 60) return `${seconds.toFixed(0)} s ago`;
  if (seconds < 3600) return `${(seconds / 60).toFixed(0)} min ago`;
  return `${(seconds / 3600).toFixed(1)} h ago`;
}

function within(seconds) {
  return seconds < 120 ? `${Math.round(seconds)} s` : `${Math.ceil(seconds / 60)} min`;
}

function errorText(errors) {
  const parts = Object.entries(errors || {}).filter(([, n]) => n > 0).map(([k, n]) => `${k} ${n}`);
  return parts.length ? parts.join(", ") : "none";
}

function remember(device, values) {
  for (const v of values) {
    const number = Number(v.text);
    if (v.quality !== "good" || Number.isNaN(number)) continue;
    const key = `${device}/${v.point}`;
    const list = history.get(key) || [];
    if (list.length === 0 || list[list.length - 1].time !== v.time) list.push({ time: v.time, value: number });
    while (list.length > 10) list.shift();
    history.set(key, list);
  }
}

// --- session ------------------------------------------------------------------------------

async function loadSession() {
  session = await api("GET", "/api/session");
  // Who and with what role: a named user, or the shared password with the name typed.
  const as = session.shared ? "shared password" : session.role;
  document.getElementById("who-name").textContent = session.signed_in ? `Signed in: ${session.who} (${as})` : "";
  document.getElementById("sign-out").hidden = !session.signed_in;
  document.getElementById("sign-in-link").hidden = session.signed_in || !session.can_sign_in;
}

document.getElementById("sign-out").addEventListener("click", async () => {
  await api("POST", "/api/logout");
  await loadSession();
  route();
});

function loginPage() {
  const status = el("p", { role: "status", "aria-live": "polite" });
  const form = el(
    "form",
    { id: "login-form" },
    el("label", {}, "User name (with the shared password: your name, kept with every write)", el("input", { name: "name", id: "login-name", autocomplete: "username", autocapitalize: "none", required: true })),
    el("label", {}, "Password", el("input", { name: "password", id: "login-password", type: "password", autocomplete: "current-password", required: true })),
    el("div", { class: "actions" }, el("button", { class: "primary", type: "submit", id: "login-submit", text: "Sign in" })),
    status,
  );
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const data = new FormData(form);
    try {
      await api("POST", "/api/login", { name: data.get("name"), password: data.get("password") });
      await loadSession();
      if (!events) connect();
      const next = sessionStorage.getItem("after-login") || "#/";
      if (location.hash === next) route(); else location.hash = next;
    } catch (error) {
      status.className = "error";
      status.textContent = error.message;
    }
  });
  let intro;
  if (!session.can_sign_in) {
    intro = session.local
      ? "No users (gateway users add) and no password (GATEWAY_WEB__PASSWORD) are configured: this page is read-only."
      : "No users (gateway users add) and no password (GATEWAY_WEB__PASSWORD) are configured: from another machine this page cannot be read at all.";
  } else {
    intro = session.local
      ? "Writes and calibrations need you to sign in."
      : "From another machine, reading this page needs you to sign in too, as do writes and calibrations.";
  }
  show(el("h1", { text: "Sign in" }), el("p", { text: intro }), session.can_sign_in ? form : "");
  const first = document.getElementById("login-name");
  if (first) first.focus();
}

function needSession(what) {
  if (session.signed_in && !session.can_write) return el("p", { class: "warning", text: `${what} needs the operator role; you sign in as a ${session.role}.` });
  if (session.signed_in) return null;
  sessionStorage.setItem("after-login", location.hash);
  return el("p", { class: "warning" }, `${what} needs you to `, el("a", { href: "#/login", text: "sign in" }), ".");
}

// --- the event stream ----------------------------------------------------------------------

let events = null;
function connect() {
  if (events) events.close();
  events = new EventSource("/api/events");
  events.addEventListener("state", (event) => {
    latest = JSON.parse(event.data);
    connection.textContent = `Live · ${new Date(latest.time).toLocaleTimeString()}`;
    for (const device of latest.devices) remember(device.name, device.values);
    updateChain(latest.records);
    if (onState) onState(latest);
  });
  events.addEventListener("error", () => {
    connection.textContent = "Connection lost: retrying…";
  });
}

// --- the live page ------------------------------------------------------------------------

// A name with a chance to wrap after each underscore (measurement_status on a phone).
function breakable(text) {
  const parts = String(text).split("_");
  return parts.flatMap((part, i) => (i < parts.length - 1 ? [`${part}_`, el("wbr")] : [part]));
}

// A value of the register map: a number or a date is never broken inside itself; a date is
// shown without its "T" and zone (the full text in its title), its seconds where not :00;
// text may wrap between its words.
const ISO_DATE = /^(\d{4}-\d\d-\d\d)T(\d\d:\d\d)(:\d\d)?([+-]\d\d:\d\d|Z)?$/;
function valueText(value) {
  if (!value) return el("span", { class: "v" });
  const text = value.text;
  const date = ISO_DATE.exec(text);
  if (date) {
    const seconds = date[3] && date[3] !== ":00" ? date[3] : "";
    return el("span", { class: "v nowrap", title: text, "data-text": text, text: `${date[1]} ${date[2]}${seconds}` });
  }
  if (numeric(text)) return el("span", { class: "v nowrap", "data-text": text, text });
  // Text may wrap between its words (at spaces, and after "_"), never inside one.
  const words = String(text).split(/(?<=[_\s])/).flatMap((word, i) => [i ? el("wbr") : null, el("span", { class: "w nowrap", text: word })]);
  return el("span", { class: "v", "data-text": text }, words);
}

function valuesTable(device, values) {
  const rows = values.map((v) => {
    const bits = (v.bits || []).filter((b) => b.set).map((b) => b.name);
    const text = v.bits ? (bits.length ? bits.join(", ") : "no bit set") : v.text;
    const isNumber = !v.bits && numeric(text);
    return el(
      "tr",
      { "data-point": v.point, class: `q-${v.quality}` },
      el("th", { scope: "row" }, breakable(v.point)),
      el("td", { class: isNumber ? "num" : "bits", "data-value": v.point }, breakable(text)),
      el("td", { class: "unit", text: v.unit }),
      el("td", { class: `q-${v.quality}`, text: v.quality === "fault" ? "fault" : v.quality.replace("_", " ") }),
    );
  });
  return el(
    "table",
    { class: "values", "aria-label": `Values of ${device}` },
    el("thead", {}, el("tr", {}, el("th", { text: "Point" }), el("th", { text: "Value" }), el("th", { text: "Unit" }), el("th", { text: "Quality" }))),
    el("tbody", {}, rows),
  );
}

function deviceCard(device) {
  return el(
    "section",
    { class: "card device", "data-device": device.name, "aria-label": device.name },
    el(
      "header",
      {},
      el("h2", {}, el("a", { href: `#/device/${encodeURIComponent(device.name)}`, text: device.name })),
      onlineBadge(device.online),
    ),
    el("p", { class: "meta" }, `${device.profile} · ${device.bus} · address ${device.address}`),
    device.online === false && device.reason ? el("p", { class: "error", text: device.reason }) : null,
    valuesTable(device.name, device.values),
    el(
      "p",
      { class: "meta" },
      `Last good response: ${ago(device.last_good_age_s)} · errors: ${errorText(device.errors)}`,
    ),
  );
}

// The host clock: until it is synchronised (or trusted by the config), set-clock and every
// calibration, which write a date into the sensor, are refused; the page says so first.
// A list (empty or one note), to spread among the children.
function clockNote(clock) {
  if (!clock || clock.synchronized) return [];
  if (clock.trusted) {
    return [el("p", { class: "meta", id: "clock-note", text: "The host clock is not synchronised; dates are written into sensors as it stands (clock.trust_unsynchronised)." })];
  }
  return [
    el(
      "p",
      { class: "warning", role: "alert", id: "clock-note" },
      `The host clock is not synchronised: ${clock.problem}. Calibrations and setting a sensor's clock write a date, so they are refused until it is. To fix: ${clock.fix}.`,
    ),
  ];
}

function livePage() {
  const body = el("div", { id: "live" });
  const render = (state) => {
    const paused = state.lines.filter((l) => l.paused);
    body.replaceChildren(
      ...clockNote(state.clock),
      ...paused.map((l) => el("p", { class: "warning", role: "alert" }, `Line ${l.name}: polling is paused (${l.paused}); its values are not being read.`)),
      el("div", { class: "grid" }, state.devices.map(deviceCard)),
    );
  };
  show(el("h1", { text: "Live values" }), body);
  onState = render;
  if (latest) render(latest);
}

// --- sensor care -----------------------------------------------------------------------------

const CARE_WORDS = { ok: "ok", due_soon: "due soon", due: "due", maintenance: "maintenance", unknown: "unknown" };
const WEEKDAYS = ["Sun", "Mon", "Tue", "Wed", "Thu", "Fri", "Sat"];
const MONTHS = ["Jan", "Feb", "Mar", "Apr", "May", "Jun", "Jul", "Aug", "Sep", "Oct", "Nov", "Dec"];

// A date as an operator reads it, in this browser's time zone: "Tue 3 Dec" (the year only
// when it is not this one), never broken across two lines.
function day(iso) {
  const d = new Date(iso);
  const year = d.getFullYear() === new Date().getFullYear() ? "" : ` ${d.getFullYear()}`;
  const text = `${WEEKDAYS[d.getDay()]} ${d.getDate()} ${MONTHS[d.getMonth()]}${year}`;
  return el("span", { class: "nowrap", title: d.toLocaleString(), text });
}

function percent(ratio) {
  return el("span", { class: "nowrap", text: `${Math.round(100 * ratio)} %` });
}

// The figures in plain words: when to calibrate, the slope and where it is going, the cap.
function careFigures(doc) {
  const parts = [];
  if (doc.due) {
    const every = doc.interval_days === 7 ? "weekly" : `every ${doc.interval_days} days`;
    const late = doc.assessed_at !== null && new Date(doc.due) <= new Date(doc.assessed_at);
    parts.push(late ? "Calibration due since " : "Calibrate by ", day(doc.due));
    if (doc.last_calibration) parts.push(" (last ", day(doc.last_calibration), `, ${every}). `);
    else parts.push(". ");
  } else if (doc.last_calibration) {
    parts.push("Last calibrated ", day(doc.last_calibration), ". ");
  }
  if (doc.slope_ratio !== null && doc.slope_ratio !== undefined) {
    parts.push("Slope ", percent(doc.slope_ratio), " of nominal");
    const week = doc.slope_trend ? doc.slope_trend.per_week : null;
    if (week !== null && Math.abs(week) >= 0.005) parts.push(` and ${week < 0 ? "falling" : "rising"} `, percent(Math.abs(week)), " a week");
    else if (week !== null) parts.push(", steady");
    if (doc.projection) parts.push(": membrane and electrolyte about ", day(doc.projection.at), " at this rate");
    else if (doc.slope_limit !== null && doc.slope_ratio < doc.slope_limit) parts.push(", below the ", percent(doc.slope_limit), " limit");
    parts.push(". ");
  }
  if (doc.cap_usage !== null && doc.cap_usage !== undefined) parts.push("Cap ", percent(doc.cap_usage), " used.");
  return parts.length ? el("p", { class: "care-figures" }, parts) : null;
}

function careCard(doc) {
  const offer = doc.calibration;
  const urgent = ["due", "due_soon", "maintenance"].includes(doc.state);
  return el(
    "section",
    { class: `card care care-${doc.state}`, "data-device": doc.device, "data-state": doc.state, "aria-label": doc.device },
    el(
      "header",
      {},
      el("h2", {}, el("a", { href: `#/device/${encodeURIComponent(doc.device)}` }, breakable(doc.device))),
      el("span", { class: `badge care-badge care-${doc.state}`, text: CARE_WORDS[doc.state] || doc.state }),
    ),
    el("p", { class: "meta" }, `${doc.profile} · ${doc.bus}`),
    el("ul", { class: "reasons" }, doc.reasons.map((reason) => el("li", { text: reason }))),
    careFigures(doc),
    offer
      ? el("p", { class: "actions" }, el("a", {
        class: urgent ? "button primary" : "button",
        href: `#/calibrate/${encodeURIComponent(doc.device)}/${offer.procedure}`,
        "data-calibrate": offer.procedure,
        text: `Calibrate: ${offer.title}`,
      }))
      : null,
  );
}

function carePage() {
  const body = el("div", { id: "care", "aria-live": "polite" });
  let shown = null; // the care_version of the documents shown
  let asked = 0;
  const load = async () => {
    const ask = ++asked;
    try {
      const docs = await api("GET", "/api/care");
      if (ask !== asked) return; // a newer answer is on its way
      body.replaceChildren(docs.length
        ? el("div", { class: "grid" }, docs.map(careCard))
        : el("p", { class: "meta", text: "Care follows no device here (care is off, or no family it knows is configured)." }));
    } catch (error) {
      body.replaceChildren(el("p", { class: "error", text: error.message }));
    }
  };
  show(
    el("h1", { text: "Sensor care" }),
    el("p", { class: "meta", text: "What each sensor needs and when, most urgent first, from the records the sensors keep." }),
    body,
  );
  onState = (state) => {
    if (state.care_version === shown) return;
    shown = state.care_version;
    load();
  };
  if (latest) onState(latest); else load();
  timer = setInterval(load, 30000); // dates move on by themselves: "due soon" becomes "due"
}

// --- bus health ------------------------------------------------------------------------------

function healthPage() {
  const body = el("div", { id: "health" });
  const render = (state) => {
    const lines = state.lines.map((line) =>
      el(
        "section",
        { class: "card", "data-line": line.name },
        el("h2", { text: `Line ${line.name}` }),
        line.paused ? el("p", { class: "warning", text: `Polling paused: ${line.paused}` }) : null,
        el(
          "table",
          {},
          el("tbody", {}, [
            ["Port", line.port_open ? "open" : "closed"],
            ["Port failures", line.port_failures],
            ["Requests", line.requests],
            ["Responses", line.responses],
            ["Retries", line.retries],
            ["Errors", errorText(line.errors)],
            ["Bus utilisation", `${(100 * line.utilisation).toFixed(1)} %`],
            ["Mean latency", line.mean_latency_ms === null ? "-" : `${line.mean_latency_ms} ms`],
          ].map(([k, v]) => el("tr", {}, el("th", { scope: "row", text: k }), el("td", { class: "num", text: v })))),
        ),
      ),
    );
    const rows = state.devices.map((d) =>
      el(
        "tr",
        { "data-device": d.name },
        el("th", { scope: "row" }, el("a", { href: `#/device/${encodeURIComponent(d.name)}`, text: d.name })),
        el("td", {}, onlineBadge(d.online)),
        el("td", { class: "num", text: d.requests }),
        el("td", { class: "num", text: d.retries }),
        el("td", { text: errorText(d.errors) }),
        el("td", { class: "num wide-only", text: d.lag_s === null ? "-" : `${d.lag_s} s` }),
        el("td", { class: "num wide-only", text: d.missed_deadlines }),
      ),
    );
    body.replaceChildren(
      el("div", { class: "grid" }, lines),
      el("h2", { text: "Devices" }),
      el(
        "div",
        { class: "scroll" },
        el(
          "table",
          {},
          el("thead", {}, el("tr", {}, ["Device", "State", "Requests", "Retries", "Errors by kind"].map((t) => el("th", { text: t })), el("th", { class: "wide-only", text: "Lag" }), el("th", { class: "wide-only", text: "Missed" }))),
          el("tbody", {}, rows),
        ),
      ),
      el("p", { class: "meta", "data-broker": "mqtt", text: brokerLine(state.mqtt) }),
      ...(state.mqtt.sparkplug ? [el("p", { class: "meta", "data-broker": "sparkplug", text: sparkplugLine(state.mqtt.sparkplug) })] : []),
      ...(state.mqtt.identity_conflict ? [el("p", { class: "error", role: "alert", text: `MQTT stood down: ${state.mqtt.identity_conflict}` })] : []),
      ...clockNote(state.clock),
    );
  };
  show(el("h1", { text: "Bus health" }), body);
  onState = render;
  if (latest) render(latest);
}

function plural(count, word) {
  return `${count} ${word}${count === 1 ? "" : "es"}`;
}

// The broker connection in one line: with a list of servers, which one and how often it moved.
function brokerLine(mqtt) {
  if (!mqtt.enabled) return "MQTT: off";
  const where = mqtt.servers > 1 ? ` to ${mqtt.server} (${mqtt.position} of ${mqtt.servers}) · ${plural(mqtt.switches, "switch")}` : "";
  return `MQTT: ${mqtt.connected ? "connected" : "not connected"}${where} · queue ${mqtt.queue_depth}`;
}

function sparkplugLine(sparkplug) {
  const host = sparkplug.host_online ? "host online" : "host not online";
  return `Sparkplug: ${sparkplug.connected ? "connected" : "not connected"} to ${sparkplug.server} · ${host} · ${plural(sparkplug.switches, "switch")}`;
}

// --- one device -------------------------------------------------------------------------------

function writeForm(device, point) {
  const input = el("input", { name: "value", "aria-label": `New value of ${point.name}`, required: true });
  const status = el("span", { role: "status", "aria-live": "polite" });
  const form = el(
    "form",
    { class: "write-form", "data-write": point.name },
    input,
    el("button", { type: "submit", text: "Write" }),
    status,
  );
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    status.className = "";
    status.textContent = "writing…";
    try {
      const result = await api("POST", `/api/devices/${encodeURIComponent(device)}/points/${encodeURIComponent(point.name)}`, { value: input.value });
      status.className = "ok";
      status.textContent = `${result.written ? "written" : "unchanged"}; holds ${JSON.stringify(result.value)}`;
    } catch (error) {
      status.className = "error";
      status.textContent = error.message;
    }
  });
  return form;
}

function readAllButton(device) {
  const status = el("span", { role: "status", "aria-live": "polite" });
  const button = el("button", { type: "button", id: "read-all", text: "Read every register now" });
  button.addEventListener("click", async () => {
    button.disabled = true;
    status.className = "";
    status.textContent = "reading…";
    try {
      const result = await api("POST", `/api/devices/${encodeURIComponent(device)}/read`);
      for (const v of result.values) {
        const cell = view.querySelector(`#register-map td[data-value="${CSS.escape(v.point)}"]`);
        if (cell) cell.replaceChildren(valueText(v));
      }
      status.className = "ok";
      status.textContent = `${result.values.length} values read`;
    } catch (error) {
      status.className = "error";
      status.textContent = error.message;
    } finally {
      button.disabled = false;
    }
  });
  return el("div", { class: "actions" }, button, status);
}

async function devicePage(name) {
  let data;
  try {
    data = await api("GET", `/api/devices/${encodeURIComponent(name)}`);
  } catch (error) {
    show(el("h1", { text: name }), el("p", { class: "error", text: error.message }));
    return;
  }
  const identity = el(
    "table",
    { id: "identity" },
    el("tbody", {}, Object.entries(data.identity).map(([k, v]) => el("tr", {}, el("th", { scope: "row" }, breakable(k)), el("td", { class: "map-value" }, valueText({ text: v }))))),
  );
  const procedures = data.procedures.length
    ? el("ul", { id: "procedures" }, data.procedures.map((p) => el("li", {}, el("a", { href: `#/calibrate/${encodeURIComponent(name)}/${p.id}`, text: p.title }))))
    : el("p", { class: "meta", text: "No guided calibration for this family." });
  const rows = data.points.flatMap((p) => {
    const row = el(
      "tr",
      { "data-point": p.name },
      el("td", { class: "num wide-only", text: p.address }),
      // On a phone the address goes under the name: its own column left no room for values.
      el("th", { scope: "row", title: p.description }, breakable(p.name), el("span", { class: "addr phone-only", text: p.address })),
      el("td", { class: "map-value", "data-value": p.name }, valueText(p.value)),
      el("td", { class: "unit", text: p.unit }),
      el("td", { class: "wide-only", text: `${p.type} ${p.access}${p.storage ? " " + p.storage : ""}` }),
    );
    // The write form (or why there is none) on a row of its own, the width of the table:
    // beside the value it squeezed the value's column on a phone.
    let below = null;
    if (p.writable && session.can_write) below = writeForm(name, p);
    else if (p.refused && p.access === "rw" && session.can_write) below = el("span", { class: "meta refused", text: `Not writable: ${p.refused}` });
    if (!below) return [row];
    row.classList.add("has-write");
    return [row, el("tr", { class: "write-row", "data-write-row": p.name }, el("td", { class: "wide-only" }), el("td", { colspan: 4 }, below))];
  });
  show(
    el("p", {}, el("a", { href: "#/", text: "← Live values" })),
    el("h1", {}, `${data.name} `, onlineBadge(data.online)),
    el("p", { class: "meta" }, `${data.profile} · line ${data.bus} · address ${data.address}`),
    el("h2", { text: "Identity" }),
    identity,
    el("h2", { text: "Calibration" }),
    needSession("Calibrating"),
    await underWay(name, null),
    procedures,
    el("p", {}, el("a", { href: `#/verify/${encodeURIComponent(name)}`, id: "verify-link", text: "Verify against a grab sample" }), " · ", el("a", { href: `#/records?device=${encodeURIComponent(name)}`, id: "records-link", text: "Its records" })),
    el("h2", { text: "Register map" }),
    session.signed_in ? readAllButton(name) : null,
    el(
      "div",
      { class: "scroll" },
      el(
        "table",
        { id: "register-map" },
        el("thead", {}, el("tr", {}, el("th", { class: "wide-only", text: "Addr" }), el("th", { text: "Point" }), el("th", { text: "Value" }), el("th", { text: "Unit" }), el("th", { class: "wide-only", text: "Type" }))),
        el("tbody", {}, rows),
      ),
    ),
  );
  timer = setInterval(async () => {
    try {
      const fresh = await api("GET", `/api/devices/${encodeURIComponent(name)}`);
      for (const p of fresh.points) {
        const cell = view.querySelector(`#register-map td[data-value="${CSS.escape(p.name)}"]`);
        const shown = cell && cell.querySelector(".v");
        if (cell && p.value && (!shown || shown.dataset.text !== p.value.text)) cell.replaceChildren(valueText(p.value));
      }
    } catch { /* the next one */ }
  }, 3000);
}

// --- guided calibration ----------------------------------------------------------------------

// A field of the calibration catalogue (its default, bounds and choices are the server's,
// the same as `gateway calibrate`'s); an optional choice without a default may stay blank.
function field(f) {
  if (f.kind === "choice") {
    const choices = !f.required && f.default === null ? ["", ...f.choices] : f.choices;
    return el(
      "label",
      {},
      f.label,
      el("select", { name: f.name, id: `f-${f.name}` }, choices.map((c) => el("option", { value: c, selected: c === (f.default ?? ""), text: c || "(as the sensor holds it)" }))),
    );
  }
  return el(
    "label",
    {},
    f.label,
    el("input", {
      name: f.name,
      id: `f-${f.name}`,
      type: "number",
      step: f.kind === "integer" ? "1" : "any",
      min: f.min,
      max: f.max,
      inputmode: "decimal",
      value: f.default === null ? "" : f.default,
      required: f.required,
    }),
  );
}

function watchPanel(device, points) {
  const panel = el("section", { class: "card", id: "settle", "aria-label": "Live reading" });
  const render = (state) => {
    const found = state.devices.find((d) => d.name === device);
    const items = points.map((point) => {
      const v = found && found.values.find((x) => x.point === point);
      const recent = (history.get(`${device}/${point}`) || []).map((h) => h.value);
      const spread = recent.length > 1 ? Math.max(...recent) - Math.min(...recent) : null;
      return el(
        "div",
        { "data-watch": point },
        el("div", { class: "meta", text: point }),
        el("div", { class: `big q-${quality(v)}`, text: v ? `${v.text} ${v.unit}` : "–" }),
        el("div", { class: "meta", text: spread === null ? "waiting for readings…" : `last ${recent.length} readings within ${spread.toPrecision(3)}` }),
      );
    });
    panel.replaceChildren(el("h2", { text: "Live reading: wait for it to settle" }), el("div", { class: "grid" }, items));
  };
  return { panel, render };
}

// How a run ended: a short verdict first; the checks, then the values in a fold.
function outcomeView(run) {
  const o = run.outcome;
  const good = o ? o.ok && run.phase === "done" : false;
  const heading = o ? (run.phase === "done" ? o.status.replace("_", " ") : run.phase) : run.phase;
  return el(
    "section",
    { id: "result", role: "alert" },
    el("h2", { class: good ? "ok" : "error", text: heading }),
    el("p", { id: "verdict", text: run.verdict || "" }),
    run.error && !(run.verdict || "").includes(run.error) ? el("p", { class: "error", text: run.error }) : null,
    o && o.checks.length ? el("table", {}, el("tbody", {}, o.checks.map((c) => el("tr", {}, el("th", { scope: "row", text: c.name }), el("td", { class: c.ok ? "ok" : "error", text: c.ok ? "ok" : "MISMATCH" }))))) : null,
    o && o.warnings.length ? el("ul", {}, o.warnings.map((w) => el("li", { class: "error", text: w }))) : null,
    o ? el("details", { id: "result-detail" }, el("summary", { text: "Values read and computed" }), el("pre", { text: JSON.stringify(o.values, null, 1) })) : null,
  );
}

// The calibrations under way on a device, for any signed-in user to open, take over or
// cancel (a run left at its question on a locked phone blocks the device until then).
async function underWay(device, onMine) {
  const box = el("div", { id: "under-way" });
  let data;
  try {
    data = await api("GET", `/api/calibrations?device=${encodeURIComponent(device)}`);
  } catch {
    return box;
  }
  for (const run of data.runs) {
    if (run.mine && onMine) { onMine(run); continue; }
    const waiting = run.phase === "confirm"
      ? `is waiting for its confirmation${run.answer_within_s !== null ? ` (ends by itself in ${within(run.answer_within_s)})` : ""}`
      : `is ${run.phase}`;
    const status = el("span", { role: "status" });
    const buttons = [];
    if (session.can_write && !run.mine && run.can_cancel) {
      const take = el("button", { type: "button", id: "take-over", text: "Take over" });
      take.addEventListener("click", async () => {
        try {
          await api("POST", `/api/calibrations/${run.id}/take-over`);
          const target = `#/calibrate/${encodeURIComponent(device)}/${run.procedure.id}`;
          if (location.hash === target) route(); else location.hash = target;
        } catch (error) { status.className = "error"; status.textContent = error.message; }
      });
      const stop = el("button", { class: "danger", type: "button", id: "cancel-other", text: "Cancel it (nothing is written)" });
      stop.addEventListener("click", async () => {
        try {
          await api("POST", `/api/calibrations/${run.id}/cancel`);
          status.className = "ok"; status.textContent = "cancelled";
          stop.disabled = true; take.disabled = true;
        } catch (error) { status.className = "error"; status.textContent = error.message; }
      });
      buttons.push(take, stop);
    }
    box.append(el("div", { class: "warning", "data-run": run.id }, el("p", {}, `A ${run.procedure.title} calibration started by ${run.who} ${waiting}.`), buttons.length ? el("div", { class: "actions" }, buttons, status) : null));
  }
  return box;
}

async function calibratePage(device, procedureId) {
  let data;
  try {
    data = await api("GET", `/api/devices/${encodeURIComponent(device)}`);
  } catch (error) {
    show(el("p", { class: "error", text: error.message }));
    return;
  }
  const procedure = data.procedures.find((p) => p.id === procedureId);
  if (!procedure) {
    show(el("p", { class: "error", text: `${device} has no calibration ${procedureId}` }));
    return;
  }
  const watch = watchPanel(device, procedure.watch);
  const status = el("div", { id: "run", "aria-live": "polite" });
  // The start is signed (21 CFR Part 11 §11.200): the password again, and why, for the record.
  const password = el("input", { id: "sign-password", type: "password", autocomplete: "current-password", required: true });
  const reason = el("input", { id: "sign-reason", autocomplete: "off" });
  const form = el(
    "form",
    { id: "calibration-form" },
    procedure.fields.map(field),
    el("label", {}, "Reason (optional, kept in the record)", reason),
    el("label", {}, `Your password again, to sign as ${session.who || "you"}`, password),
    el("div", { class: "actions" }, el("button", { class: "primary", type: "submit", id: "start", text: "Start" })),
  );
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const inputs = {}; // the procedure's fields: the password and the reason have no name
    for (const [k, v] of new FormData(form).entries()) inputs[k] = v;
    try {
      const run = await api("POST", "/api/calibrations", { device, procedure: procedureId, inputs, password: password.value, reason: reason.value });
      password.value = "";
      form.querySelector("button").disabled = true;
      follow(run.id, status, form);
    } catch (error) {
      status.replaceChildren(el("p", { class: "error", role: "alert", text: error.message }));
    }
  });
  let resumed = null;
  const others = await underWay(device, (run) => { if (run.procedure.id === procedureId) resumed = run; });
  show(
    el("p", {}, el("a", { href: `#/device/${encodeURIComponent(device)}`, text: `← ${device}` })),
    el("h1", { text: `${procedure.title}: ${device}` }),
    el("p", { text: procedure.hint }),
    needSession("Calibrating"),
    others,
    watch.panel,
    el("h2", { text: "Calibration" }),
    form,
    status,
  );
  onState = watch.render;
  if (latest) watch.render(latest);
  if (resumed) { // a run of this session (a reloaded page, or one taken over): follow it
    form.querySelector("button").disabled = true;
    follow(resumed.id, status, form);
  }
}

// The run as it goes: steps are appended, and the controls are rebuilt only when the phase
// or what may be done changes, so the keyboard focus stays where the operator left it.
function follow(id, status, form) {
  const phase = el("p", { id: "phase" });
  const progress = el("p", { id: "progress", class: "meta" });
  const steps = el("ol", { class: "steps", id: "steps" });
  const fold = el("details", { id: "steps-fold" }, el("summary", { id: "steps-summary", text: "Steps" }), steps);
  const controls = el("div");
  const errors = el("div", { "aria-live": "assertive" });
  status.replaceChildren(phase, progress, controls, fold, errors);
  let shownControls = null;
  const tick = async () => {
    let run;
    try {
      run = await api("GET", `/api/calibrations/${id}`);
    } catch (error) {
      errors.replaceChildren(el("p", { class: "error", text: error.message }));
      return;
    }
    phase.dataset.phase = run.phase;
    phase.textContent = `Phase: ${run.phase}`;
    for (const step of run.steps.slice(steps.children.length)) {
      steps.append(el("li", { class: `s-${step.kind}` }, `${step.kind}: ${step.text}`));
    }
    const last = run.steps[run.steps.length - 1];
    progress.textContent = run.phase === "confirm" ? "" : last ? last.text : "starting…";
    fold.querySelector("summary").textContent = `Every step, with the registers (${run.steps.length})`;
    const state = `${run.phase}/${run.can_cancel}/${run.mine}`;
    if (state === shownControls) return;
    shownControls = state;
    const parts = [];
    let focus = null;
    if (run.phase === "confirm" && run.mine) {
      const yes = el("button", { class: "primary", type: "button", id: "confirm-write", text: "Write to the sensor" });
      const no = el("button", { class: "danger", type: "button", id: "decline", text: "Do not write (ends the calibration)" });
      yes.addEventListener("click", () => answer(id, true, errors));
      no.addEventListener("click", () => answer(id, false, errors));
      const deadline = run.answer_within_s === null ? "" : ` Without an answer it ends by itself in ${within(run.answer_within_s)}, nothing written.`;
      parts.push(el(
        "section",
        { class: "warning", id: "question", role: "alertdialog", "aria-label": "Confirm the writes" },
        el("p", { id: "summary", class: "summary", text: run.summary }),
        el("p", { class: "meta", text: `Nothing is written until you say so.${deadline}` }),
        el("div", { class: "actions" }, yes, no),
        el("details", { id: "question-detail" }, el("summary", { text: "Register detail" }), el("pre", { text: [run.detail, ...run.steps.filter((s) => s.kind === "plan").map((s) => s.text)].join("\n") })),
      ));
      focus = yes;
    } else if (run.can_cancel && run.mine) {
      const cancel = el("button", { class: "danger", type: "button", id: "cancel", text: "Cancel (nothing is written)" });
      cancel.addEventListener("click", async () => {
        try {
          await api("POST", `/api/calibrations/${id}/cancel`);
        } catch (error) {
          errors.replaceChildren(el("p", { class: "error", text: error.message }));
        }
      });
      parts.push(el("div", { class: "actions" }, cancel));
      if (!focus && controls.contains(document.activeElement)) focus = cancel;
    } else if (!run.mine && ["running", "confirm"].includes(run.phase)) {
      parts.push(el("p", { class: "warning", text: `${run.who} has taken this calibration over.` }));
    }
    if (run.phase === "writing") parts.push(el("p", { class: "warning", text: "Writing: this cannot be cancelled now." }));
    const finished = !["running", "confirm", "writing"].includes(run.phase);
    if (finished) {
      parts.push(outcomeView(run));
      form.querySelector("button").disabled = false;
      clearInterval(timer);
      timer = null;
    }
    controls.replaceChildren(...parts);
    if (focus) focus.focus();
  };
  clearInterval(timer);
  timer = setInterval(tick, 400);
  tick();
}

async function answer(id, confirm, errors) {
  try {
    await api("POST", `/api/calibrations/${id}/answer`, { confirm });
  } catch (error) {
    errors.replaceChildren(el("p", { class: "error", text: error.message }));
  }
}

// --- scanning a line ------------------------------------------------------------------------

function scanPage() {
  const lines = latest ? latest.lines.map((l) => l.name) : [];
  const status = el("div", { id: "scan-status", "aria-live": "polite" });
  const form = el(
    "form",
    { id: "scan-form" },
    el("label", {}, "Line", el("select", { name: "bus", id: "scan-bus" }, lines.map((n) => el("option", { value: n, text: n })))),
    el("label", {}, "Addresses", el("input", { name: "addresses", id: "scan-addresses", value: "1-247" })),
    el("div", { class: "actions" }, el("button", { class: "danger", type: "submit", id: "scan-start", text: "Stop polling and scan" })),
  );
  const poll = (bus) => {
    clearInterval(timer);
    timer = setInterval(async () => {
      try {
        const job = await api("GET", `/api/lines/${encodeURIComponent(bus)}/scan`);
        const found = job.report ? job.report.devices : [];
        status.replaceChildren(
          el("p", { id: "scan-progress" }, `${job.running ? "Scanning" : "Done"}: ${job.probed}/${job.total} addresses, ${job.found} found, ${job.elapsed_s} s`),
          job.error ? el("p", { class: "error", text: job.error }) : null,
          job.running ? el("p", { class: "warning", role: "alert", id: "scan-paused", text: `Polling of line ${bus} is paused while it is scanned.` }) : null,
          found.length ? el("table", { id: "scan-found" }, el("tbody", {}, found.map((d) => el("tr", { "data-address": d.address }, el("td", { class: "num", text: d.address }), el("td", { text: d.profile || d.family || "?" }), el("td", { class: "bits", text: Object.entries(d.details || {}).filter(([, v]) => v !== null).map(([k, v]) => `${k}=${v}`).join(", ") }))))) : null,
          job.report ? el("pre", { text: job.report.config }) : null,
        );
        if (!job.running) clearInterval(timer);
      } catch (error) {
        status.replaceChildren(el("p", { class: "error", text: error.message }));
      }
    }, 700);
  };
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const data = new FormData(form);
    try {
      await api("POST", `/api/lines/${encodeURIComponent(data.get("bus"))}/scan`, { addresses: data.get("addresses") });
      poll(data.get("bus"));
    } catch (error) {
      status.replaceChildren(el("p", { class: "error", role: "alert", text: error.message }));
    }
  });
  show(
    el("h1", { text: "Scan a line" }),
    el("p", { class: "warning", role: "note" }, "While a line is scanned its polling stops: no values of its sensors are read, published or alarmed until the scan ends. Scan only a line that is idle or being commissioned."),
    needSession("Scanning"),
    form,
    status,
  );
  onState = (state) => {
    const select = document.getElementById("scan-bus");
    if (select && select.options.length === 0) {
      select.replaceChildren(...state.lines.map((l) => el("option", { value: l.name, text: l.name })));
    }
  };
}

// --- the records: every change to a sensor, with the chain's verdict -------------------------

const KINDS = ["write", "outcome", "calibration", "verification", "history", "reload", "clock", "feeds", "correction"];
let chain = { seq: null, checking: false, verdict: null };

// The footer: the chain's head from the live stream, its verdict from /api/records (the whole
// chain checked in the gateway) whenever the head moves; a copy kept elsewhere compares both.
async function updateChain(head) {
  const footer = document.getElementById("chain");
  if (!head) { footer.hidden = true; return; }
  footer.hidden = false;
  const text = document.getElementById("chain-head");
  text.textContent = `Records: head ${head.seq} · ${head.short}`;
  text.title = head.hash;
  if (chain.seq === head.seq || chain.checking) return;
  chain.checking = true;
  try {
    const data = await api("GET", "/api/records?limit=0");
    chain.seq = data.head.seq;
    chain.verdict = data.verdict;
    showVerdict(document.getElementById("chain-verdict"), data.verdict);
  } catch { /* the next head */ } finally {
    chain.checking = false;
  }
}

function showVerdict(node, verdict) {
  node.className = verdict.intact ? "ok" : "error";
  node.textContent = verdict.intact
    ? `chain intact (${verdict.checked} records checked)`
    : `chain BROKEN at record ${verdict.broken_at}: ${verdict.problem}`;
}

function utc(iso) {
  // "2025-06-01T08:03:04.123+00:00" → "2025-06-01 08:03:04" (the records' own time, UTC).
  const match = /^(\d{4}-\d\d-\d\d)T(\d\d:\d\d:\d\d)/.exec(iso || "");
  return match ? `${match[1]} ${match[2]}` : iso || "";
}

function change(p) {
  const found = p.as_found_text || (p.sent_text ? "" : "–");
  const left = p.as_left_text || (p.sent_text ? `(sent ${p.sent_text})` : "");
  const unit = p.unit ? ` ${p.unit}` : "";
  if (!left) return `${found}${unit}`;
  return `${found || "–"} → ${left}${unit}`;
}

// A verification's point: the sensor's value against the grab sample's.
function cellOf(record, p) {
  if (!p) return "";
  if (record.kind === "verification" && record.data.reference !== undefined) {
    const unit = p.unit ? ` ${p.unit}` : "";
    return `${p.as_found_text}${unit} (reference ${record.data.reference})`;
  }
  return change(p);
}

// A write's result is pending until its outcome record: both are shown, the outcome named.
function resultOf(record) {
  if (!record.outcome) return record.result;
  return `${record.result} → ${record.outcome.result} (#${record.outcome.seq})`;
}

function recordRows(record) {
  const points = record.points.length ? record.points : [null];
  return points.map((p, i) => el(
    "tr",
    { "data-seq": record.seq, "data-kind": record.kind, class: `r-${record.result}` },
    el("td", { class: "num", text: i ? "" : record.seq }),
    el("td", { class: "nowrap", text: i ? "" : utc(record.time) }),
    el("td", { title: record.detail }, i ? "" : record.user, !i && record.signed ? el("span", { class: "meta", text: " (signed)" }) : null),
    el("td", { text: i ? "" : record.via }),
    el("td", {}, i ? "" : breakable(record.device || "")),
    el("td", { text: i ? "" : record.action }),
    el("td", {}, p ? breakable(p.point) : ""),
    el("td", { class: "change", text: cellOf(record, p) }),
    el("td", { class: `result res-${record.outcome ? record.outcome.result : record.result}`, text: i ? "" : resultOf(record) }),
    el("td", { text: i ? "" : record.reason }),
    el("td", { class: "note", text: i ? "" : record.note }),
  ));
}

function recordsPage() {
  const params = new URLSearchParams(location.hash.split("?")[1] || "");
  const devices = latest ? latest.devices.map((d) => d.name) : [];
  const device = el("select", { name: "device", id: "records-device" }, el("option", { value: "", text: "every device" }), devices.map((n) => el("option", { value: n, text: n, selected: n === params.get("device") })));
  const kind = el("select", { name: "kind", id: "records-kind" }, el("option", { value: "", text: "every kind" }), KINDS.map((k) => el("option", { value: k, text: k, selected: k === params.get("kind") })));
  const verdict = el("p", { id: "records-verdict", role: "status" });
  const status = el("p", { id: "records-status", class: "meta", "aria-live": "polite" });
  const body = el("tbody", { id: "records-rows" });
  const filters = el(
    "form",
    { id: "records-filters", class: "filters no-print" },
    el("label", {}, "Device", device),
    el("label", {}, "Kind", kind),
    el("div", { class: "actions" }, el("button", { type: "button", id: "records-print", text: "Print", onclick: () => window.print() })),
  );
  const load = async () => {
    const query = new URLSearchParams();
    if (device.value) query.set("device", device.value);
    if (kind.value) query.set("kind", kind.value);
    status.textContent = "reading…";
    try {
      const data = await api("GET", `/api/records?${query}`);
      body.replaceChildren(...data.records.flatMap(recordRows));
      showVerdict(verdict, data.verdict);
      verdict.textContent = `Head ${data.head.seq} · ${data.head.short} · ${verdict.textContent}`;
      verdict.title = data.head.hash;
      const chosen = [device.value || "every device", kind.value || "every kind"].join(", ");
      status.textContent = data.records.length
        ? `${data.count} records (${chosen}), newest first${data.more ? `; older ones too: the newest ${data.limit} are shown (gateway records export has them all)` : ""}.`
        : `No records (${chosen}).`;
    } catch (error) {
      status.className = "error";
      status.textContent = error.message;
    }
  };
  const refilter = () => {
    const query = new URLSearchParams();
    if (device.value) query.set("device", device.value);
    if (kind.value) query.set("kind", kind.value);
    window.history.replaceState(null, "", `#/records${query.toString() ? `?${query}` : ""}`);
    load();
  };
  device.addEventListener("change", refilter);
  kind.addEventListener("change", refilter);
  filters.addEventListener("submit", (event) => { event.preventDefault(); refilter(); });
  show(
    el("h1", { text: "Records" }),
    el("p", { class: "meta", text: "Every change to a sensor, every calibration and verification, in the gateway's append-only, hash-chained record store. Times are UTC." }),
    filters,
    verdict,
    status,
    el(
      "div",
      { class: "scroll" },
      el(
        "table",
        { id: "records-table" },
        el("thead", {}, el("tr", {}, ["#", "Time (UTC)", "Who", "Via", "Device", "Action", "Point", "As found → as left", "Result", "Reason", "Note"].map((t) => el("th", { scope: "col", text: t })))),
        body,
      ),
    ),
  );
  load();
}

// --- grab-sample verification: a phone at the basin ----------------------------------------

function pad(n) { return String(n).padStart(2, "0"); }

// Now, as a datetime-local input shows it: this browser's local time, to the minute.
function localNow() {
  const d = new Date();
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())}T${pad(d.getHours())}:${pad(d.getMinutes())}`;
}

// A datetime-local value (this browser's local time) as ISO 8601 with its offset.
function withOffset(value) {
  const d = new Date(value);
  const offset = -d.getTimezoneOffset();
  const sign = offset < 0 ? "-" : "+";
  const hours = pad(Math.floor(Math.abs(offset) / 60));
  const minutes = pad(Math.abs(offset) % 60);
  return `${value.length === 16 ? `${value}:00` : value}${sign}${hours}:${minutes}`;
}

function verificationOutcome(device, result) {
  const unit = result.unit ? ` ${result.unit}` : "";
  const deviation = `${result.deviation > 0 ? "+" : ""}${result.deviation}`;
  const offer = !result.passed && result.calibration
    ? el("p", { class: "actions" }, el("a", { class: "button primary", id: "verify-calibrate", href: `#/calibrate/${encodeURIComponent(device)}/${result.calibration.procedure}`, text: `Calibrate now: ${result.calibration.title}` }))
    : null;
  return el(
    "section",
    { id: "verify-outcome", class: result.passed ? "card" : "card warning", role: "alert", "data-passed": String(result.passed) },
    el("h2", { class: result.passed ? "ok" : "error", text: result.passed ? "Passed" : "Failed: outside the acceptance limit" }),
    el(
      "table",
      {},
      el("tbody", {}, [
        ["Sensor", `${result.sensor_value}${unit} (read ${utc(result.sensor_time)} UTC)`],
        ["Reference", `${result.reference}${unit}`],
        ["Deviation", `${deviation}${unit}`],
        ["Limit", `±${result.limit}${unit}`],
        ["Rule", result.rule.name],
        ["Record", `#${result.record}`],
      ].map(([k, v]) => el("tr", {}, el("th", { scope: "row", text: k }), el("td", { "data-field": k.toLowerCase(), text: v })))),
    ),
    offer,
  );
}

async function verifyPage(device) {
  const names = latest ? latest.devices.map((d) => d.name) : [];
  if (!device) {
    if (!names.length) {
      show(el("h1", { text: "Verify against a grab sample" }), el("p", { class: "meta", text: "Waiting for the gateway's devices…" }));
      onState = (state) => { if (state.devices.length) verifyPage(state.devices[0].name); };
      return;
    }
    device = names[0];
  }
  let form;
  try {
    form = await api("GET", `/api/devices/${encodeURIComponent(device)}/verification`);
  } catch (error) {
    show(el("h1", { text: "Verify against a grab sample" }), el("p", { class: "error", text: error.message }));
    return;
  }
  const pick = el("select", { id: "verify-device", "aria-label": "Device" }, (names.length ? names : [device]).map((n) => el("option", { value: n, text: n, selected: n === device })));
  pick.addEventListener("change", () => { location.hash = `#/verify/${encodeURIComponent(pick.value)}`; });
  const sampled = el("input", { name: "sampled_at", id: "verify-sampled", type: "datetime-local", value: localNow() });
  let sampledEdited = false; // untouched: the sample is "now", the time the gateway gets it
  sampled.addEventListener("input", () => { sampledEdited = true; });
  const password = el("input", { name: "password", id: "verify-password", type: "password", autocomplete: "current-password", required: true });
  const status = el("div", { id: "verify-status", "aria-live": "polite" });
  const rule = form.rule
    ? `Accepted within ±${form.rule.absolute} ${form.rule.unit || ""} or ±${Math.round(100 * form.rule.relative)} % of the reference, whichever is larger (${form.rule.name}).`
    : "This device has no acceptance rule: the gateway refuses its verification until verification.rules names one.";
  const entry = el(
    "form",
    { id: "verify-form" },
    el("label", {}, `Reference value (${form.point})`, el("input", { name: "reference", id: "verify-reference", type: "number", step: "any", min: "0", inputmode: "decimal", required: true })),
    el("label", {}, "Unit", el("input", { name: "unit", id: "verify-unit", value: form.unit || "", autocapitalize: "none" })),
    el("label", {}, "Method", el("input", { name: "method", id: "verify-method", value: form.method, required: true })),
    el("label", {}, "Instrument (optional)", el("input", { name: "instrument", id: "verify-instrument", autocomplete: "off" })),
    el("label", {}, "Sampled at (this phone's local time)", sampled),
    el("label", {}, "Reason (optional, kept in the record)", el("input", { name: "reason", id: "verify-reason", autocomplete: "off" })),
    el("label", {}, `Your password again, to sign as ${session.who || "you"}`, password),
    el("div", { class: "actions" }, el("button", { class: "primary", type: "submit", id: "verify-submit", text: "Record the verification" })),
  );
  entry.addEventListener("submit", async (event) => {
    event.preventDefault();
    const data = new FormData(entry);
    const body = {
      reference: Number(data.get("reference")),
      unit: data.get("unit") || null,
      method: data.get("method"),
      instrument: data.get("instrument") || null,
      reason: data.get("reason") || null,
      password: password.value,
    };
    if (sampledEdited && sampled.value) body.sampled_at = withOffset(sampled.value);
    const button = entry.querySelector("button");
    button.disabled = true;
    status.replaceChildren(el("p", { class: "meta", text: "judging…" }));
    try {
      const result = await api("POST", `/api/devices/${encodeURIComponent(device)}/verify`, body);
      password.value = "";
      status.replaceChildren(verificationOutcome(device, result));
    } catch (error) {
      status.replaceChildren(el("p", { class: "error", role: "alert", id: "verify-error", text: error.message }));
    } finally {
      button.disabled = false;
    }
  });
  show(
    el("h1", { text: "Verify against a grab sample" }),
    el("label", {}, "Device", pick),
    el("p", { class: "meta" }, `${form.profile}: compares ${form.point}. ${rule} Nothing is written to the sensor.`),
    needSession("Verifying"),
    entry,
    status,
    form.calibration
      ? el("p", { class: "meta" }, "If it fails: ", el("a", { href: `#/calibrate/${encodeURIComponent(device)}/${form.calibration.procedure}`, text: form.calibration.title }), ".")
      : null,
  );
}

// --- routing ---------------------------------------------------------------------------------

function route() {
  clearInterval(timer);
  timer = null;
  onState = null;
  const parts = location.hash.replace(/^#\/?/, "").split("?")[0].split("/").map(decodeURIComponent);
  for (const link of document.querySelectorAll("nav a")) {
    link.toggleAttribute("aria-current", link.getAttribute("href") === `#/${parts[0] || ""}`);
    if (link.hasAttribute("aria-current")) link.setAttribute("aria-current", "page");
  }
  if (!session.can_read && parts[0] !== "login") {
    sessionStorage.setItem("after-login", location.hash);
    loginPage();
    return;
  }
  switch (parts[0]) {
    case "login": loginPage(); break;
    case "care": carePage(); break;
    case "health": healthPage(); break;
    case "device": devicePage(parts[1]); break;
    case "calibrate": calibratePage(parts[1], parts[2]); break;
    case "scan": scanPage(); break;
    case "records": recordsPage(); break;
    case "verify": verifyPage(parts[1]); break;
    default: livePage();
  }
  view.focus({ preventScroll: true });
}

window.addEventListener("hashchange", route);
(async () => {
  await loadSession();
  if (session.can_read) connect();
  route();
})();
