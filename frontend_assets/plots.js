// Plots drawn in the browser as inline SVG (scales with the page, text stays selectable,
// nothing to download): confusion / error matrices as heat maps, scores as grouped bars.

import { h, num, s } from "./dom.js";

const SERIES_COLOURS = ["#2a6f97", "#e9a23b", "#2a9d8f", "#9d4edd", "#e76f51"];

function text(x, y, content, attrs = {}) {
  return s("text", { x, y, ...attrs }, content);
}

/** White -> deep blue for a share in 0..1. */
function heat(share) {
  const t = Math.max(0, Math.min(1, share || 0));
  const from = [244, 247, 251];
  const to = [22, 72, 138];
  const c = from.map((f, i) => Math.round(f + (to[i] - f) * t));
  return `rgb(${c[0]},${c[1]},${c[2]})`;
}

/**
 * A heat map of MATRIX (rows = reference, columns = predicted): each cell coloured by its
 * share of its row (the row's recall), labelled with that share and the count.
 */
export function heatmap(matrix, { rows, cols, title, rowAxis = "reference", colAxis = "predicted" }) {
  const n = matrix.length;
  const m = matrix[0]?.length ?? 0;
  const cellW = 92;
  const cellH = 48;
  const left = 120;
  const top = 62;
  // wide enough for the title too (a long one was clipped at both ends)
  const width = Math.max(left + m * cellW + 12, 24 + 8 * title.length);
  const height = top + n * cellH + 14;
  const svg = s("svg", {
    class: "plot heatmap",
    viewBox: `0 0 ${width} ${height}`,
    width,
    role: "img",
    "aria-label": title,
  });
  svg.append(text(width / 2, 16, title, { class: "plot-title", "text-anchor": "middle" }));
  svg.append(
    text(left + (m * cellW) / 2, 34, `${colAxis} →`, { class: "axis-label", "text-anchor": "middle" }),
  );
  cols.forEach((name, j) => {
    svg.append(
      text(left + j * cellW + cellW / 2, top - 8, name, { class: "tick", "text-anchor": "middle" }),
    );
  });
  svg.append(
    text(12, top + (n * cellH) / 2, `${rowAxis} →`, {
      class: "axis-label",
      "text-anchor": "middle",
      transform: `rotate(-90 12 ${top + (n * cellH) / 2})`,
    }),
  );
  matrix.forEach((row, i) => {
    const total = row.reduce((a, b) => a + (b || 0), 0);
    svg.append(
      text(left - 8, top + i * cellH + cellH / 2 + 4, rows[i], { class: "tick", "text-anchor": "end" }),
    );
    row.forEach((count, j) => {
      const share = total ? (count || 0) / total : 0;
      const x = left + j * cellW;
      const y = top + i * cellH;
      const dark = share > 0.55;
      const label = total ? `${(share * 100).toFixed(1)} %` : "–";
      svg.append(
        s(
          "g",
          { class: i === j ? "cell diagonal" : "cell" },
          s(
            "rect",
            { x, y, width: cellW - 2, height: cellH - 2, rx: 3, fill: heat(share) },
            s("title", {}, `${rows[i]} → ${cols[j]}: ${num(count)} of ${num(total)}`),
          ),
          text(x + cellW / 2 - 1, y + 20, label, {
            class: dark ? "cell-value dark" : "cell-value",
            "text-anchor": "middle",
          }),
          text(x + cellW / 2 - 1, y + 36, num(count), {
            class: dark ? "cell-count dark" : "cell-count",
            "text-anchor": "middle",
          }),
        ),
      );
    });
  });
  return svg;
}

/**
 * Grouped bars: GROUPS = [{label, values: {series: value}}], values in 0..max (percent by
 * default); missing or NaN values are marked n/a.
 */
export function bars(groups, { series, title, max = 100, unit = "%", seriesLabels = {} }) {
  const barW = 18;
  const gap = 4;
  const groupW = series.length * (barW + gap) + 26;
  const left = 22 + 7 * num(max).length; // room for the widest tick label
  const top = 30;
  const plotH = 150;
  const legendH = 22;
  const width = Math.max(left + groups.length * groupW + 16, 260);
  const height = top + plotH + 44 + legendH;
  const svg = s("svg", {
    class: "plot bars",
    viewBox: `0 0 ${width} ${height}`,
    width,
    role: "img",
    "aria-label": title,
  });
  svg.append(text(width / 2, 16, title, { class: "plot-title", "text-anchor": "middle" }));
  // counts below 4 get one tick per whole number (quarters of 1 would all read 0 or 1)
  const steps = Number.isInteger(max) && max > 0 && max < 4 ? max : 4;
  for (let k = 0; k <= steps; k += 1) {
    const value = (max * k) / steps;
    const y = top + plotH - (plotH * k) / steps;
    svg.append(s("line", { x1: left, x2: width - 8, y1: y, y2: y, class: k ? "gridline" : "axis" }));
    svg.append(text(left - 5, y + 4, `${num(value)}`, { class: "tick", "text-anchor": "end" }));
  }
  svg.append(
    text(10, top + plotH / 2, unit, {
      class: "axis-label",
      "text-anchor": "middle",
      transform: `rotate(-90 10 ${top + plotH / 2})`,
    }),
  );
  groups.forEach((group, g) => {
    const x0 = left + 14 + g * groupW;
    series.forEach((name, k) => {
      const value = group.values[name];
      const x = x0 + k * (barW + gap);
      const ok = typeof value === "number" && Number.isFinite(value);
      const hgt = ok ? (plotH * Math.max(0, Math.min(max, value))) / max : 0;
      const label = seriesLabels[name] || name;
      if (ok) {
        svg.append(
          s(
            "rect",
            {
              x,
              y: top + plotH - hgt,
              width: barW,
              height: hgt,
              fill: SERIES_COLOURS[k % SERIES_COLOURS.length],
              class: "bar",
            },
            s("title", {}, `${group.label}, ${label}: ${num(value, 1)} ${unit}`),
          ),
        );
      } else {
        svg.append(
          text(x + barW / 2, top + plotH - 4, "n/a", {
            class: "tick na",
            "text-anchor": "middle",
            transform: `rotate(-90 ${x + barW / 2} ${top + plotH - 4})`,
          }),
        );
      }
    });
    svg.append(
      text(x0 + (series.length * (barW + gap)) / 2 - gap / 2, top + plotH + 16, group.label, {
        class: "tick",
        "text-anchor": "middle",
      }),
    );
  });
  let lx = left;
  const ly = top + plotH + 38;
  series.forEach((name, k) => {
    const label = seriesLabels[name] || name;
    svg.append(
      s("rect", { x: lx, y: ly - 9, width: 10, height: 10, fill: SERIES_COLOURS[k % SERIES_COLOURS.length] }),
    );
    svg.append(text(lx + 14, ly, label, { class: "tick" }));
    lx += 24 + label.length * 7;
  });
  return svg;
}

/** A figure: the plot with a caption under it. */
export function figure(plot, caption) {
  return h("figure", { class: "figure" }, plot, caption ? h("figcaption", {}, caption) : null);
}
