// The lab's web page: live rows from the server's event stream, times in
// the reader's zone, sortable tables. The server renders (and escapes)
// all HTML; this script only moves it into place.
"use strict";

(() => {
  const clock = (ms) => {
    const date = new Date(ms);
    const today = new Date().toDateString() === date.toDateString();
    return today
      ? date.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit", second: "2-digit" })
      : date.toLocaleString([], { month: "short", day: "numeric", hour: "2-digit", minute: "2-digit" });
  };

  const relative = (ms) => {
    const seconds = Math.round((Date.now() - ms) / 1000);
    const span = Math.abs(seconds);
    const say = (n, unit) => (seconds >= 0 ? `${n} ${unit} ago` : `in ${n} ${unit}`);
    if (span < 3) return "just now";
    if (span < 90) return say(span, "s");
    if (span < 90 * 60) return say(Math.round(span / 60), "min");
    if (span < 36 * 3600) return say(Math.round(span / 3600), "h");
    return clock(ms);
  };

  const formatTimes = (root) => {
    for (const t of root.querySelectorAll("time[data-unix-ms]")) {
      const ms = Number(t.dataset.unixMs);
      if (!Number.isFinite(ms)) continue;
      t.textContent = t.dataset.style === "relative" ? relative(ms) : clock(ms);
      t.title = new Date(ms).toString();
    }
  };

  const setLive = (state, text) => {
    const live = document.getElementById("live");
    if (!live) return;
    live.dataset.state = state;
    live.textContent = text;
  };

  // One event: the banner and every env's row, as the server renders them.
  const applyUpdate = (html) => {
    const fragment = document.createElement("template");
    fragment.innerHTML = html;
    const banner = fragment.content.querySelector("#banner");
    const current = document.getElementById("banner");
    if (banner && current) current.replaceWith(banner);
    const fresh = new Map(
      [...fragment.content.querySelectorAll("tr[data-env]")].map((row) => [row.dataset.env, row]),
    );
    // A page about one env keeps its row only.
    for (const row of document.querySelectorAll("tbody[data-single] tr[data-env]")) {
      const update = fresh.get(row.dataset.env);
      if (update) row.replaceWith(update.cloneNode(true));
    }
    const all = document.getElementById("env-rows");
    if (all) all.replaceChildren(...[...fresh.values()].map((row) => row.cloneNode(true)));
    formatTimes(document);
  };

  const follow = () => {
    if (!document.querySelector("table[data-live]") || !window.EventSource) return;
    setLive("connecting", "Connecting to live updates…");
    const source = new EventSource("/events");
    source.addEventListener("envs", (event) => {
      applyUpdate(event.data);
      setLive("live", "Live: the page updates as the envs change.");
    });
    // The browser reconnects by itself (the server asks for 2 s).
    source.onerror = () => setLive("reconnecting", "Live updates interrupted: reconnecting…");
  };

  const sortable = (table) => {
    const headers = [...table.querySelectorAll("thead th")];
    headers.forEach((th, column) => {
      const button = th.querySelector("button[data-sort]");
      if (!button) return;
      button.addEventListener("click", () => {
        const ascending = th.getAttribute("aria-sort") !== "ascending";
        const numeric = button.dataset.sort === "number";
        const body = table.tBodies[0];
        const value = (row) => row.cells[column]?.dataset.value ?? "";
        const rows = [...body.rows].sort((a, b) => {
          const order = numeric
            ? Number(value(a)) - Number(value(b))
            : value(a).localeCompare(value(b));
          return ascending ? order : -order;
        });
        body.replaceChildren(...rows);
        for (const other of headers) other.setAttribute("aria-sort", "none");
        th.setAttribute("aria-sort", ascending ? "ascending" : "descending");
      });
    });
  };

  // The booking form: the start is typed in the reader's zone; the
  // server gets it as Unix ms (without this script it reads UTC).
  const pad = (n) => String(n).padStart(2, "0");
  const localInput = (date) =>
    `${date.getFullYear()}-${pad(date.getMonth() + 1)}-${pad(date.getDate())}T${pad(date.getHours())}:${pad(date.getMinutes())}`;
  const slotForm = (form) => {
    const start = form.elements.start;
    const ms = form.elements.start_unix_ms;
    if (!start || !ms) return;
    // The server's default (next full hour, UTC) shown in local time.
    if (start.defaultValue && !form.dataset.kept) {
      const utc = new Date(`${start.defaultValue}:00Z`);
      if (!Number.isNaN(utc.getTime())) start.value = localInput(utc);
    }
    const zone = form.querySelector("[data-zone]");
    if (zone) zone.textContent = `(${Intl.DateTimeFormat().resolvedOptions().timeZone || "local time"})`;
    form.addEventListener("submit", () => {
      const local = new Date(start.value);
      ms.value = Number.isNaN(local.getTime()) ? "" : String(local.getTime());
    });
  };

  // Thumbnails: a fresh frame every few seconds (the server pulls at most
  // one per env every 2 s, whatever the number of viewers).
  const refreshThumbnails = () => {
    const images = document.querySelectorAll("img[data-thumbnail]");
    if (!images.length) return;
    setInterval(() => {
      if (document.hidden) return;
      for (const img of images) {
        const url = new URL(img.src, window.location.href);
        url.searchParams.set("t", String(Date.now()));
        img.src = url.pathname + url.search;
      }
    }, 3000);
  };

  document.addEventListener("DOMContentLoaded", () => {
    refreshThumbnails();
    document.querySelectorAll("form[data-slot-form]").forEach(slotForm);
    formatTimes(document);
    document.querySelectorAll("table.sortable").forEach(sortable);
    follow();
    // "… ago" stays true between events.
    setInterval(() => formatTimes(document), 1000);
  });
})();
