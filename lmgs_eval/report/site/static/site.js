// lmgs-eval report: sortable tables, the family filter, the charts' hover card. Plain JS, no library.
"use strict";

function sortKey(td, kind) {
  const raw = td ? td.getAttribute("data-sort") : null;
  if (kind === "num") {
    const v = parseFloat(raw);
    return Number.isFinite(v) ? v : null;
  }
  return raw === null ? "" : raw.toLowerCase();
}

function sortTable(table, th) {
  const col = Number(th.dataset.col);
  const kind = th.dataset.kind;
  // first click: best first (by the column's arrow); again: the other way
  const higher = th.dataset.higher === "true";
  const prev = th.getAttribute("aria-sort");
  let dir;
  if (prev === null || prev === "none") dir = kind === "num" ? (higher ? "descending" : "ascending") : "ascending";
  else dir = prev === "ascending" ? "descending" : "ascending";
  table.querySelectorAll("th").forEach((h) => h.setAttribute("aria-sort", "none"));
  th.setAttribute("aria-sort", dir);
  const body = table.tBodies[0];
  const rows = Array.from(body.rows);
  const sign = dir === "ascending" ? 1 : -1;
  rows.sort((a, b) => {
    const x = sortKey(a.cells[col], kind), y = sortKey(b.cells[col], kind);
    if (x === null && y === null) return 0;
    if (x === null) return 1;  // rows without a value go last either way
    if (y === null) return -1;
    return (x < y ? -1 : x > y ? 1 : 0) * sign;
  });
  rows.forEach((r) => { r.classList.remove("rule"); body.appendChild(r); });
}

function initSortable() {
  document.querySelectorAll("table.sortable").forEach((table) => {
    table.querySelectorAll("th[data-col]").forEach((th) => {
      th.setAttribute("aria-sort", "none");
      th.tabIndex = 0;
      th.addEventListener("click", () => sortTable(table, th));
      th.addEventListener("keydown", (e) => { if (e.key === "Enter") sortTable(table, th); });
    });
  });
}

function initFamilyFilter() {
  const box = document.getElementById("family-filter");
  if (!box) return;
  const apply = () => {
    const on = new Set(Array.from(box.querySelectorAll("input:checked")).map((i) => i.value));
    document.querySelectorAll("table.sortable tbody tr[data-family]").forEach((tr) => {
      const fam = tr.dataset.family;
      tr.hidden = fam !== "" && !on.has(fam);
    });
  };
  box.addEventListener("change", apply);
  apply();
}

function initHoverCard() {
  const card = document.getElementById("hover-card");
  if (!card) return;
  const show = (g, x, y) => {
    card.textContent = g.dataset.info;
    card.hidden = false;
    card.style.left = (x + 14) + "px";
    card.style.top = (y + 14) + "px";
  };
  document.querySelectorAll("svg.chart g.pt").forEach((g) => {
    g.addEventListener("mousemove", (e) => show(g, e.pageX, e.pageY));
    g.addEventListener("mouseleave", () => { card.hidden = true; });
    g.addEventListener("focus", () => {
      const r = g.getBoundingClientRect();
      show(g, r.right + window.scrollX, r.top + window.scrollY);
    });
    g.addEventListener("blur", () => { card.hidden = true; });
    g.addEventListener("click", () => { if (g.dataset.run) window.location.href = "runs/" + g.dataset.run + ".html"; });
  });
}

initSortable();
initFamilyFilter();
initHoverCard();
