// Small DOM helpers. Text always goes in as text nodes, never as HTML, so names and messages
// from the server cannot inject markup.

const SVG_NS = "http://www.w3.org/2000/svg";

function setAttributes(el, attrs) {
  for (const [key, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (key === "class") el.setAttribute("class", value);
    else if (key === "dataset") Object.assign(el.dataset, value);
    else if (key.startsWith("on") && typeof value === "function") {
      el.addEventListener(key.slice(2), value);
    } else if (key === "value" && "value" in el) el.value = value;
    else el.setAttribute(key, value === true ? "" : value);
  }
}

export function append(el, children) {
  for (const child of children.flat(Infinity)) {
    if (child === null || child === undefined || child === false) continue;
    el.append(child instanceof Node ? child : String(child));
  }
  return el;
}

/** h("a", {href: "#/x"}, "text", child, ...): an HTML element. */
export function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  setAttributes(el, attrs);
  return append(el, children);
}

/** An SVG element (same calling convention as h). */
export function s(tag, attrs = {}, ...children) {
  const el = document.createElementNS(SVG_NS, tag);
  setAttributes(el, attrs);
  return append(el, children);
}

export function clear(el) {
  el.replaceChildren();
  return el;
}

// --- formatting ---------------------------------------------------------------------------

const INT = new Intl.NumberFormat("en-US");

export function num(value, digits = 0) {
  if (value === null || value === undefined) return "";
  if (typeof value !== "number") return String(value);
  if (!Number.isFinite(value)) return "n/a";
  if (digits === 0 && Number.isInteger(value)) return INT.format(value);
  return value.toLocaleString("en-US", {
    minimumFractionDigits: digits,
    maximumFractionDigits: digits,
  });
}

/** A percentage the API already gives in % (papers' metrics); null/NaN as n/a. */
export function pct(value, digits = 1) {
  if (value === null || value === undefined || !Number.isFinite(value)) return "n/a";
  return `${value.toFixed(digits)}`;
}

export function when(iso) {
  if (!iso) return "";
  const date = new Date(iso);
  if (Number.isNaN(date.getTime())) return iso;
  return date.toLocaleString("en-GB", {
    year: "numeric",
    month: "short",
    day: "2-digit",
    hour: "2-digit",
    minute: "2-digit",
    second: "2-digit",
  });
}

export function duration(seconds) {
  if (seconds === null || seconds === undefined) return "";
  if (seconds < 60) return `${seconds.toFixed(1)} s`;
  const m = Math.floor(seconds / 60);
  if (m < 60) return `${m} min ${Math.round(seconds - m * 60)} s`;
  return `${Math.floor(m / 60)} h ${m % 60} min`;
}

export function bytes(n) {
  if (n < 1024) return `${n} B`;
  const units = ["KB", "MB", "GB", "TB"];
  let value = n / 1024;
  let unit = 0;
  while (value >= 1024 && unit < units.length - 1) {
    value /= 1024;
    unit += 1;
  }
  return `${value.toFixed(1)} ${units[unit]}`;
}

// --- shared widgets -----------------------------------------------------------------------

export const ACTIVE = new Set(["queued", "running"]);

export function statusBadge(status, extra = "") {
  return h("span", { class: `badge status-${status}`, "data-status": status }, status, extra);
}

/** A progress bar for a job; `set(job)` moves it. */
export function progressBar(job, { label = true } = {}) {
  const fill = h("div", { class: "fill" });
  const text = label ? h("span", { class: "progress-text" }) : null;
  const el = h(
    "div",
    { class: "progress", role: "progressbar", "aria-valuemin": "0", "aria-valuemax": "100" },
    fill,
    text,
  );
  const set = (j) => {
    const percent = Math.max(0, Math.min(100, Math.round((j.progress ?? 0) * 1000) / 10));
    fill.style.width = `${percent}%`;
    el.dataset.status = j.status;
    el.dataset.job = j.id;
    el.setAttribute("aria-valuenow", String(percent));
    if (text) text.textContent = `${percent.toFixed(0)} %`;
  };
  if (job) set(job);
  return { el, set };
}

/** A simple bar for a share (0..1) with a caption. */
export function shareBar(share, caption) {
  const percent = Math.max(0, Math.min(100, (share || 0) * 100));
  const fill = h("div", { class: "fill" });
  fill.style.width = `${percent}%`;
  return h(
    "div",
    { class: "progress share", role: "progressbar", "aria-valuenow": percent.toFixed(0) },
    fill,
    h("span", { class: "progress-text" }, caption),
  );
}

export function table(headers, rows, attrs = {}) {
  return h(
    "table",
    { class: "grid", ...attrs },
    h("thead", {}, h("tr", {}, headers.map((x) => h("th", {}, x)))),
    h(
      "tbody",
      {},
      rows.map((row) => h("tr", {}, row.map((cell) => h("td", {}, cell)))),
    ),
  );
}

/** A facts list: [[label, value], ...]; `wide` flows the pairs into columns. */
export function facts(pairs, { wide = false } = {}) {
  return h(
    "dl",
    { class: wide ? "facts wide" : "facts" },
    pairs.map(([k, v]) => [h("dt", {}, k), h("dd", {}, v)]),
  );
}

export function note(text) {
  return h("p", { class: "note" }, text);
}

export function section(title, ...children) {
  return h("section", { class: "card" }, h("h2", {}, title), ...children);
}
