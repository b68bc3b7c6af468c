// A survey's sensor kind (the server's app.core.sensors): the scanner that recorded it, which
// decides the models its runs use. Told by the reader or the point times at import, otherwise
// declared: in the import and upload forms, later on the survey page (PATCH /surveys/{id}).

import { api, hasRole } from "./api.js";
import { h } from "./dom.js";

export const SENSORS = [
  { value: "rotating", text: "Rotating (spinning multi-beam)" },
  { value: "profile", text: "Profile (MMS line scanner)" },
];

const UNKNOWN_HINT =
  "The sensor kind is unknown: runs need it declared (rotating or profile), as they use the model for that kind.";

/** The forms' "Sensor" select: detect from the data (nothing sent) or a declared kind. */
export function sensorSelect(id) {
  return h(
    "select",
    { id, name: "sensor" },
    h("option", { value: "" }, "Detect from the data"),
    SENSORS.map((s) => h("option", { value: s.value }, s.text)),
  );
}

/** A kind as a badge, how it was told as its title. */
export function sensorBadge(kind, note) {
  const shown = kind || "unknown";
  const title = note || (shown === "unknown" ? UNKNOWN_HINT : "");
  return h("span", { class: `badge sensor sensor-${shown}`, "data-sensor": shown, title: title || null }, shown);
}

/** The survey page's sensor block: the kind, how it was told, a hint while unknown, and (for
 * annotators) a select + save that declares it; `onChange(survey)` gets the server's answer. */
export function sensorBlock(ctx, survey, onChange) {
  const el = h("div", { class: "sensor-block", id: "survey-sensor" });
  const render = (sv) => {
    const unknown = sv.sensor_kind === "unknown";
    const parts = [
      h(
        "p",
        { class: "sensor-line" },
        h("strong", {}, "Sensor "),
        sensorBadge(sv.sensor_kind, sv.sensor_note),
        sv.sensor_note ? h("span", { class: "muted" }, ` ${sv.sensor_note}`) : null,
      ),
      unknown ? h("p", { class: "sensor-hint", id: "sensor-hint", role: "note" }, UNKNOWN_HINT) : null,
    ];
    if (hasRole(ctx.user, "annotator")) parts.push(sensorForm(ctx, sv, render, onChange));
    el.replaceChildren(...parts.filter(Boolean));
  };
  render(survey);
  return el;
}

function sensorForm(ctx, survey, render, onChange) {
  const unknown = survey.sensor_kind === "unknown";
  const select = h(
    "select",
    { id: "sensor-kind", name: "sensor_kind" },
    unknown ? h("option", { value: "", disabled: true, selected: true }, "choose…") : null,
    SENSORS.map((s) => h("option", { value: s.value, selected: s.value === survey.sensor_kind }, s.text)),
  );
  const save = h("button", { type: "submit", id: "sensor-save" }, "Save");
  const form = h("form", { class: "sensor-form", id: "sensor-form" }, h("label", {}, "Declare the sensor", select), save);
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    if (!select.value || select.value === survey.sensor_kind) return;
    ctx.act(save, async () => {
      const changed = await api(`/surveys/${survey.id}`, {
        method: "PATCH",
        json: { sensor_kind: select.value },
      });
      ctx.notice(`Survey ${changed.name}: sensor declared ${changed.sensor_kind}; its runs use the ${changed.sensor_kind} models.`);
      render(changed);
      onChange?.(changed);
    });
  });
  return form;
}
