// The papers' metrics of a finished job (GET /jobs/{id} -> result.metrics) as tables and plots:
// phantom (Nagy & Benedek): confusion matrices and per-class precision / recall / F;
// clutter (Lee et al.): the error matrix, omission / commission and SA / DA / AA;
// guardrail (Matsumoto et al.): slice and point precision / recall / F.

import { vocabulary } from "./api.js";
import { h, note, num, pct, table } from "./dom.js";
import { bars, figure, heatmap } from "./plots.js";

const PRF = ["precision", "recall", "f1"];
const PRF_LABELS = { precision: "precision", recall: "recall", f1: "F" };

export function pipelineOf(kind) {
  if (kind === "run:phantom" || kind === "train:phantom") return "phantom";
  if (kind === "run:clutter" || kind === "clutter:recompute") return "clutter";
  if (kind === "run:guardrail" || kind === "guardrail:rebuild" || kind === "train:guardrail") {
    return "guardrail";
  }
  return null;
}

function isObject(value) {
  return value !== null && typeof value === "object" && !Array.isArray(value);
}

function prfRow(name, s) {
  return [name, pct(s?.precision), pct(s?.recall), pct(s?.f1), num(s?.support)];
}

/** `render(pillarNames)` (the pillar classes in label order, from the API's vocabulary) in a
 * block filled once they are read; the API's error instead if they cannot be: the dashboard
 * keeps no copy of the vocabulary and does not guess the names. */
function withPillarNames(render) {
  const block = h("div", { class: "pillar-named" });
  vocabulary().then(
    (v) => block.replaceChildren(...render(v.pillar_classes).filter(Boolean)),
    (err) =>
      block.replaceChildren(
        h("p", { class: "error" }, `The pillar class names could not be read: ${err.message}`),
      ),
  );
  return block;
}

/** Per-class precision / recall / F table of a multi-class `Scores` dict, with the macro row;
 * without its own `names`, the pillar classes (`pillarNames`) in label order when those are its
 * classes (the JSON keys may come sorted). */
export function scoresTable(scores, pillarNames) {
  const known = Object.keys(scores.classes || {});
  const names =
    scores.names || (pillarNames.every((n) => known.includes(n)) ? pillarNames : known);
  const rows = names.filter((n) => scores.classes?.[n]).map((n) => prfRow(n, scores.classes[n]));
  if (scores.macro) {
    const over = (scores.macro_classes || []).join(", ") || "classes with support";
    rows.push(prfRow(`mean (${over})`, scores.macro));
  }
  if (scores.accuracy !== undefined) rows.push(["accuracy", "", "", pct(scores.accuracy), ""]);
  return table(["class", "precision [%]", "recall [%]", "F [%]", "support"], rows, {
    class: "grid numeric",
  });
}

/** Confusion heat map and per-class bars of a multi-class `Scores` dict (its classes: its own
 * `names`, else the pillar classes in label order). */
export function scoresPlots(scores, title, pillarNames) {
  const names = scores.names || pillarNames;
  const plots = [];
  if (Array.isArray(scores.confusion) && scores.confusion.length) {
    plots.push(
      figure(
        heatmap(scores.confusion, { rows: names, cols: names, title: `confusion: ${title}` }),
        "rows: reference class; columns: predicted; share of the row and count",
      ),
    );
  }
  if (isObject(scores.classes)) {
    const groups = names
      .filter((n) => scores.classes[n])
      .map((n) => ({ label: n, values: scores.classes[n] }));
    plots.push(
      figure(
        bars(groups, { series: PRF, seriesLabels: PRF_LABELS, title: `per class: ${title}` }),
      ),
    );
  }
  return h("div", { class: "plots" }, plots);
}

function phantom(metrics) {
  const parts = [];
  const titles = {
    pillar: "pillars (after the 5x5 vote)",
    pillar_raw: "pillars (CNN only)",
    point: "points",
  };
  const present = Object.entries(titles).filter(([key]) => isObject(metrics[key]));
  if (present.length) {
    parts.push(
      withPillarNames((names) =>
        present.map(([key, title]) =>
          h(
            "div",
            { class: "metric-block", "data-metric": `phantom-${key}` },
            h("h3", {}, title),
            scoresTable(metrics[key], names),
            key === "pillar_raw" ? null : scoresPlots(metrics[key], title, names),
          ),
        ),
      ),
    );
  }
  if (isObject(metrics.phantom_points)) {
    const rows = Object.entries(metrics.phantom_points).map(([m, sc]) => prfRow(m, sc));
    parts.push(
      h(
        "div",
        { class: "metric-block" },
        h("h3", {}, "phantom points by method"),
        table(["method", "precision [%]", "recall [%]", "F [%]", "support"], rows, {
          class: "grid numeric",
        }),
      ),
    );
  }
  return parts;
}

function clutter(metrics) {
  const rows = [];
  const plots = [];
  const saBars = [];
  for (const [scope, byKind] of Object.entries(metrics)) {
    if (!isObject(byKind)) continue;
    for (const [kind, entry] of Object.entries(byKind)) {
      if (!isObject(entry)) continue;
      const em = entry.error_matrix || {};
      const sc = entry.scores || {};
      const scopeName = scope.replace(/_/g, " ");
      rows.push([
        scopeName,
        kind,
        pct(em.overall_accuracy),
        pct(em.clutter_omission),
        pct(em.clutter_commission),
        pct(em.map_omission),
        pct(em.map_commission),
        pct(sc.SA),
        pct(sc.DA),
        pct(sc.AA),
        num(em.points),
      ]);
      if (!em.points) continue; // e.g. no points in the camera view without a camera
      plots.push(
        figure(
          heatmap(
            [
              [em.map_kept ?? 0, em.map_removed ?? 0],
              [em.clutter_kept ?? 0, em.clutter_removed ?? 0],
            ],
            {
              rows: ["map", "clutter"],
              cols: ["kept", "removed"],
              title: `error matrix: ${kind}, ${scopeName}`,
              colAxis: "pipeline",
            },
          ),
          `reference: ${kind} points; share of the row and count`,
        ),
      );
      saBars.push({ label: `${kind}, ${scopeName}`, values: sc });
    }
  }
  const parts = [
    table(
      [
        "scope",
        "reference",
        "overall acc. [%]",
        "clutter omission [%]",
        "clutter commission [%]",
        "map omission [%]",
        "map commission [%]",
        "SA [%]",
        "DA [%]",
        "AA [%]",
        "points",
      ],
      rows,
      { class: "grid numeric" },
    ),
  ];
  if (saBars.length) {
    plots.push(
      figure(
        bars(saBars, { series: ["SA", "DA", "AA"], title: "static / dynamic / average accuracy" }),
      ),
    );
  }
  parts.push(h("div", { class: "plots" }, plots));
  return [h("div", { class: "metric-block", "data-metric": "clutter" }, parts)];
}

function guardrail(metrics) {
  const titles = { slice_raw: "slices (CNN)", slice: "slices (corrected)", point: "points" };
  const present = Object.entries(titles).filter(([key]) => isObject(metrics[key]));
  const parts = [];
  if (metrics.reference) parts.push(note(`reference: ${metrics.reference}`));
  parts.push(
    table(
      ["level", "precision [%]", "recall [%]", "F [%]", "support"],
      present.map(([key, title]) => prfRow(title, metrics[key])),
      { class: "grid numeric" },
    ),
  );
  if (present.length) {
    parts.push(
      h(
        "div",
        { class: "plots" },
        figure(
          bars(
            present.map(([key, title]) => ({ label: title, values: metrics[key] })),
            { series: PRF, seriesLabels: PRF_LABELS, title: "guardrail precision / recall / F" },
          ),
        ),
      ),
    );
  }
  return [h("div", { class: "metric-block", "data-metric": "guardrail" }, parts)];
}

const RENDERERS = { phantom, clutter, guardrail };

/** The metrics section of a finished run job of PIPELINE. */
export function renderMetrics(pipeline, metrics) {
  if (!isObject(metrics) || !Object.keys(metrics).length) {
    return note("No metrics: the survey has no reference labels for this pipeline.");
  }
  const render = RENDERERS[pipeline];
  if (!render) return h("pre", { class: "json" }, JSON.stringify(metrics, null, 2));
  return h("div", { class: "metrics", "data-pipeline": pipeline }, render(metrics));
}

/** A counts / timings dict as a two-column table (nested dicts flattened one level). */
export function keyValueTable(values, { unit = "" } = {}) {
  const rows = [];
  for (const [key, value] of Object.entries(values || {})) {
    if (isObject(value)) {
      for (const [k, v] of Object.entries(value)) {
        rows.push([`${key.replace(/_/g, " ")}: ${k.replace(/_/g, " ")}`, num(v, 0)]);
      }
    } else {
      const shown = typeof value === "number" && !Number.isInteger(value) ? num(value, 2) : num(value);
      rows.push([key.replace(/_/g, " "), unit ? `${shown} ${unit}` : shown]);
    }
  }
  return table(["", ""], rows, { class: "grid numeric compact" });
}

// --- trained model versions ----------------------------------------------------------------

/** The headline score of a model version: its F on held-out labels (macro for the phantom
 * network), and the baseline's when the version was fine-tuned. */
export function modelHeadline(model) {
  const v = model.metrics?.validation;
  if (!isObject(v)) return { f1: null, accuracy: null };
  const base = model.metrics?.baseline;
  const f1Of = (m) => {
    if (!isObject(m)) return null;
    if (isObject(m.macro)) return m.macro.f1;
    if (typeof m.f1 === "number") return m.f1;
    return null;
  };
  let f1 = f1Of(v);
  let detail = null;
  if (f1 === null && isObject(v.scores)) {
    // shipped guardrail classifier: one score per classifier head; the default head first
    const head = v.scores["image+geometry"] ? "image+geometry" : Object.keys(v.scores)[0];
    f1 = v.scores[head]?.f1 ?? null;
    detail = head;
  }
  return { f1, accuracy: v.accuracy ?? null, baseline: f1Of(base), detail };
}

/** The details of a model version's validation: confusion and per-class bars, or per head. */
export function modelDetails(model) {
  const v = model.metrics?.validation;
  const parts = [];
  if (!isObject(v)) return note("This version has no validation metrics.");
  if (isObject(v.classes)) {
    parts.push(
      withPillarNames((names) => [
        scoresTable(v, names),
        scoresPlots(v, "held-out validation", names),
      ]),
    );
  } else if (isObject(v.scores)) {
    const groups = Object.entries(v.scores).map(([head, sc]) => ({ label: head, values: sc }));
    parts.push(
      table(
        ["classifier head", "precision [%]", "recall [%]", "F [%]", "support"],
        groups.map((g) => prfRow(g.label, g.values)),
        { class: "grid numeric" },
      ),
    );
    parts.push(
      h(
        "div",
        { class: "plots" },
        figure(bars(groups, { series: PRF, seriesLabels: PRF_LABELS, title: "validation per head" })),
      ),
    );
  } else if (typeof v.f1 === "number") {
    const groups = [{ label: "this version", values: v }];
    if (isObject(model.metrics.baseline)) {
      groups.push({ label: "baseline", values: model.metrics.baseline });
    }
    parts.push(
      table(
        ["", "precision [%]", "recall [%]", "F [%]", "support"],
        groups.map((g) => prfRow(g.label, g.values)),
        { class: "grid numeric" },
      ),
    );
    parts.push(
      h(
        "div",
        { class: "plots" },
        figure(bars(groups, { series: PRF, seriesLabels: PRF_LABELS, title: "held-out validation" })),
      ),
    );
  }
  if (isObject(model.metrics?.baseline) && isObject(model.metrics.baseline.classes)) {
    parts.push(h("h4", {}, "the version it was fine-tuned from, on the same held-out labels"));
    parts.push(withPillarNames((names) => [scoresTable(model.metrics.baseline, names)]));
  }
  return h("div", { class: "model-details" }, parts);
}
