// dobtune's page script (put into the page by server/http_access.py, after viser's own page).
//
// 1. PNG of every chart: beside the "CSV" button of each chart's Export row (server/panels/
//    widgets.py) a "PNG" button that saves the chart as drawn here: its title, its canvas (the
//    curves and axes uPlot drew) and its legend, at print resolution (PRINT_K pixels per CSS
//    pixel, and at least PRINT_MIN_PX wide: uPlot draws the chart once more into a larger
//    canvas); a "PNG" button under the Nyquist views (SVG) too.
// 2. The loop's classic Bode (server/charts.py LOOP_MAG_CHART over LOOP_PHASE_CHART): one
//    frequency axis (a zoom of either sets both), a cursor read-out of both charts at the
//    hovered frequency (in the ".dt-loop-readout" line above them) and each margin marker
//    labelled with its value and frequency on the chart itself (so in its PNG too).
// 3. The URL keeps the view: the selected tab of the controls ("tab": Tune, Live, ...), of
//    the plots ("plot": Bode, Live traces, ...) and of the Bode tab ("bode": Decide, Responses,
//    Time, Nyquist, Suggest) live in the fragment (#tab=Live&plot=Bode&bode=Nyquist); a page
//    opened with one selects those tabs once viser has drawn them (a hidden Bode tab keeps its
//    sub-tabs, selected too; before they are drawn the fragment keeps the one asked for). The
//    token stays in the query string.
//
// 3. The candidate survives a reload: each browser tab has a candidate slot (an id kept in the
//    tab's sessionStorage: a reload keeps it, a new tab gets its own); the page's websocket
//    names it (viser's `websocket` URL parameter, `?dt_slot=<id>`), and the dashboard gives
//    the page the candidate it kept for that slot (server/candidate_store.py). This runs
//    before viser's client starts (it starts at DOMContentLoaded).
//
// viser's React client re-renders and re-mounts freely: a MutationObserver (and a slow timer,
// for URL rewrites that change no element) brings both back.
(() => {
  "use strict";
  if (window.__dobtuneView) return;
  window.__dobtuneView = true;

  // ---- the candidate's slot (before viser reads the URL) --------------------------------------

  const SLOT_KEY = "dobtune-slot";
  function slotId() {
    let id = null;
    try {
      id = sessionStorage.getItem(SLOT_KEY);
    } catch (err) {
      console.warn("dobtune: no sessionStorage; a reload starts a new candidate:", err);
    }
    if (!id || !/^[A-Za-z0-9_-]{8,64}$/.test(id)) {
      const bytes = new Uint8Array(12);
      crypto.getRandomValues(bytes);
      id = Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
      try {
        sessionStorage.setItem(SLOT_KEY, id);
      } catch (err) {
        console.warn("dobtune: the candidate slot cannot be kept:", err);
      }
    }
    return id;
  }
  // This page load's id: its websocket names it, and so do its reports of what it shows.
  const PAGE_ID = Array.from(crypto.getRandomValues(new Uint8Array(12)),
                             (b) => b.toString(16).padStart(2, "0")).join("");
  // The access token (server/http_access.py): from the page's own URL into its websocket's
  // and its reports' (no cookie: a cookie would reach every port of this host).
  const TOKEN_PARAM = (() => {
    const token = new URLSearchParams(location.search).get("token");
    return token ? "&token=" + encodeURIComponent(token) : "";
  })();
  (function nameSlot() {
    const p = new URLSearchParams(location.search);
    // viser writes the websocket's URL into the page's own unescaped (its dt_slot, dt_page and
    // token then read as parameters of the page): gone before the new one is set, else each
    // reload added one more dt_page to the address bar. The token is not set again beside it:
    // the websocket's URL carries it, and unescaped it reads as the page's own (once).
    for (const k of ["dt_slot", "dt_page", "dt_vw", "token"]) p.delete(k);
    const scheme = location.protocol === "https:" ? "wss://" : "ws://";
    p.set("websocket", scheme + location.host + location.pathname.replace(/\/$/, "") +
      "/?dt_slot=" + slotId() + "&dt_page=" + PAGE_ID + "&dt_vw=" +
      Math.round(window.innerWidth) + TOKEN_PARAM);
    history.replaceState(history.state, "", location.pathname + "?" + p.toString() +
      location.hash);
  })();

  const EXPORT_LABEL = "Export";
  // A tab group is known by one of its tabs: [fragment key, a tab label of that group, and
  // for a group inside a tab: [its group's key, that tab's label]].
  const GROUPS = [["tab", "Tune"], ["plot", "Bode"], ["bode", "Decide", ["plot", "Bode"]]];
  const PARENT = Object.fromEntries(GROUPS.filter((g) => g[2]).map((g) => [g[0], g[2]]));
  // Print resolution of the PNG exports: 3 pixels per CSS pixel, at least 1800 pixels wide.
  const PRINT_K = 3;
  const PRINT_MIN_PX = 1800;
  const printScale = (cssWidth) => Math.max(PRINT_K, PRINT_MIN_PX / Math.max(cssWidth, 1));

  // ---- PNG ---------------------------------------------------------------------------------

  function slug(title) {
    // The same rule as server/export.py export_filename.
    const s = title.toLowerCase().replace(/[^a-z0-9]+/g, "-").replace(/^-+|-+$/g, "");
    return "dobtune-" + (s || "chart");
  }

  function isExportRow(el) {
    if (!el) return false;
    const label = el.querySelector("label");
    if (!label || label.textContent.trim() !== EXPORT_LABEL) return false;
    return [...el.querySelectorAll("button")].some((b) => b.textContent.trim() === "CSV");
  }

  // The chart of an Export row: the uPlot right before it (GUI order), none if not drawn.
  function chartOfRow(row) {
    const prev = row.previousElementSibling;
    return prev ? prev.querySelector(":scope > .uplot-container .uplot") : null;
  }

  function addPngButtons() {
    for (const container of document.querySelectorAll(".uplot-container")) {
      const row = container.parentElement && container.parentElement.nextElementSibling;
      if (!isExportRow(row) || row.querySelector(".dt-png")) continue;
      const csv = [...row.querySelectorAll("button")].find(
        (b) => b.textContent.trim() === "CSV");
      const png = csv.cloneNode(true);
      png.classList.add("dt-png");
      png.removeAttribute("id");
      png.disabled = false;
      const text = png.querySelector(".mantine-Button-label") || png;
      text.textContent = "PNG";
      png.title = "the chart as drawn here, as a PNG image";
      png.addEventListener("click", (e) => {
        e.preventDefault();
        e.stopPropagation();
        const chart = chartOfRow(row);
        if (!chart) {
          console.error("dobtune: no drawn chart above this Export row");
          return;
        }
        savePng(chart).catch((err) => console.error("dobtune: PNG export:", err));
      });
      csv.parentElement.appendChild(png);
    }
  }

  // The Nyquist views are SVG (server/charts.py nyquist_svg), not uPlot: a PNG button under
  // them. Their HTML is replaced when the candidate changes; the button then comes back.
  function addNyquistButtons() {
    for (const box of document.querySelectorAll(".dt-nyquist-box")) {
      if (!box.querySelector("svg") || box.querySelector(".dt-png-nyquist")) continue;
      const b = document.createElement("button");
      b.type = "button";
      b.className = "dt-png-nyquist";
      b.textContent = "PNG";
      b.title = "the Nyquist view as drawn here, as a PNG image";
      b.style.cssText = "display:block;margin:4px 0 0 auto;font:12px sans-serif;" +
        "padding:2px 14px;border:1px solid #1f77b4;border-radius:4px;background:#fff;" +
        "color:#1f77b4;cursor:pointer";
      b.addEventListener("click", (e) => {
        e.preventDefault();
        e.stopPropagation();
        saveSvgsPng([...box.querySelectorAll("svg")], "dobtune-nyquist-speed-loop.png");
      });
      box.appendChild(b);
    }
  }

  function download(blob, name) {
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = name;
    a.style.display = "none";
    document.body.appendChild(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(a.href), 60000);
  }

  // The SVGs where they are on the screen, on one white canvas.
  function saveSvgsPng(svgs, name) {
    const rects = svgs.map((g) => g.getBoundingClientRect());
    const k = printScale(Math.max(...rects.map((r) => r.right)) -
                         Math.min(...rects.map((r) => r.left)));
    const x0 = Math.min(...rects.map((r) => r.left));
    const y0 = Math.min(...rects.map((r) => r.top));
    const out = document.createElement("canvas");
    out.width = Math.round((Math.max(...rects.map((r) => r.right)) - x0) * k);
    out.height = Math.round((Math.max(...rects.map((r) => r.bottom)) - y0) * k);
    const ctx = out.getContext("2d");
    ctx.fillStyle = "#ffffff";
    ctx.fillRect(0, 0, out.width, out.height);
    const drawn = svgs.map((g, i) => new Promise((resolve, reject) => {
      const img = new Image();
      img.onload = () => {
        const r = rects[i];
        ctx.drawImage(img, (r.left - x0) * k, (r.top - y0) * k, r.width * k, r.height * k);
        resolve();
      };
      img.onerror = () => reject(new Error("an SVG of the Nyquist view could not be drawn"));
      // Alone, an SVG has no page to inherit its font from: give it the page's.
      const copy = g.cloneNode(true);
      copy.setAttribute("style", (copy.getAttribute("style") || "") +
        ";font-family:" + getComputedStyle(g).fontFamily);
      img.src = "data:image/svg+xml;charset=utf-8," +
        encodeURIComponent(new XMLSerializer().serializeToString(copy));
    }));
    Promise.all(drawn).then(() => out.toBlob((blob) => {
      if (blob) download(blob, name);
      else console.error("dobtune: the PNG of the Nyquist view could not be made");
    }, "image/png"), (err) => console.error("dobtune:", err));
  }

  function background(el) {
    for (let e = el; e; e = e.parentElement) {
      const c = getComputedStyle(e).backgroundColor;
      if (c && c !== "transparent" && !/rgba\(.*,\s*0\)$/.test(c)) return c;
    }
    return "#ffffff";
  }

  // The uPlot `plot`'s canvas drawn again by uPlot at `scale` times its pixels (a copy; the
  // chart on the page is drawn back as it was): the canvas's backing store enlarged under a
  // matching transform, so curves, text and lines are drawn at that resolution, not scaled up.
  // uPlot caches the context's style between draws: the style goes over to the new store.
  async function canvasAt(plot, scale) {
    const canvas = plot.ctx.canvas;
    const ctx = plot.ctx;
    const props = ["font", "fillStyle", "strokeStyle", "lineWidth", "lineJoin", "lineCap",
                   "textAlign", "textBaseline"];
    const resize = (w, h, t) => {
      const keep = Object.fromEntries(props.map((p) => [p, ctx[p]]));
      const dash = ctx.getLineDash();
      canvas.width = w;
      canvas.height = h;
      Object.assign(ctx, keep);
      ctx.setLineDash(dash);
      ctx.setTransform(t, 0, 0, t, 0, 0);
    };
    const drawn = () => new Promise((resolve) => {
      const list = plot.hooks.draw || (plot.hooks.draw = []);
      const once = () => {
        const i = list.indexOf(once);
        if (i >= 0) list.splice(i, 1);
        resolve();
      };
      list.push(once);
      plot.redraw(false);
      setTimeout(once, 5000); // a chart that draws nothing (hidden) ends the wait too
    });
    const w = canvas.width;
    const h = canvas.height;
    const copy = document.createElement("canvas");
    try {
      resize(Math.round(w * scale), Math.round(h * scale), scale);
      await drawn();
      copy.width = canvas.width;
      copy.height = canvas.height;
      copy.getContext("2d").drawImage(canvas, 0, 0);
    } finally {
      resize(w, h, 1);
      await drawn();
    }
    return copy;
  }

  async function savePng(root) {
    const drawnCanvas = root.querySelector("canvas");
    const cssWidth = parseFloat(drawnCanvas.style.width) ||
      drawnCanvas.getBoundingClientRect().width || drawnCanvas.width;
    const title = ((root.querySelector(".u-title") || {}).textContent || "").trim();
    // The uPlot instance (viser's registry of its charts), for the series' dash patterns: the
    // legend's markers are drawn solid.
    const reg = (window.__viserTestpoints && window.__viserTestpoints.uplots) || {};
    const plot = (Object.values(reg).find((u) => u.chart && u.chart.root === root) || {}).chart;
    const scale = printScale(cssWidth) / (drawnCanvas.width / cssWidth);
    const canvas = plot && scale > 1 ? await canvasAt(plot, scale) : drawnCanvas;
    const k = canvas.width / cssWidth; // PNG pixels per CSS pixel
    const items = [];
    [...root.querySelectorAll(".u-legend .u-series")].forEach((tr, i) => {
      const marker = tr.querySelector(".u-marker");
      const label = tr.querySelector(".u-label");
      // Row 0 is the x series (no curve); a series switched off in the legend is not drawn.
      if (i === 0 || !marker || !label || tr.classList.contains("u-off")) return;
      const st = getComputedStyle(marker);
      const dash = plot && plot.series[i] && plot.series[i].dash;
      items.push({ text: label.textContent.trim(), color: st.borderTopColor,
                   dashed: Array.isArray(dash) ? dash.length > 0 : st.borderTopStyle !== "solid" });
    });
    const font = (px, bold) => `${bold ? "bold " : ""}${Math.round(px * k)}px sans-serif`;
    const pad = 8 * k;
    const lineH = 16 * k;
    const ctx0 = document.createElement("canvas").getContext("2d");
    // Legend layout: entries flow left to right, wrapped at the chart's width.
    ctx0.font = font(12, false);
    const rows = [[]];
    let x = pad;
    for (const it of items) {
      const w = 22 * k + ctx0.measureText(it.text).width + 14 * k;
      if (x + w > canvas.width - pad && rows[rows.length - 1].length) {
        rows.push([]);
        x = pad;
      }
      rows[rows.length - 1].push({ ...it, x });
      x += w;
    }
    // The title wrapped at whole words to the chart's width (one line ran off both edges of a
    // narrow chart).
    ctx0.font = font(13, true);
    const titleLines = [];
    for (const word of title ? title.split(/\s+/) : []) {
      const last = titleLines.length ? titleLines[titleLines.length - 1] : null;
      if (last !== null && ctx0.measureText(last + " " + word).width <= canvas.width - 2 * pad) {
        titleLines[titleLines.length - 1] = last + " " + word;
      } else titleLines.push(word);
    }
    ctx0.font = font(12, false);
    const titleLineH = 18 * k;
    const titleH = titleLines.length ? titleLines.length * titleLineH + 4 * k : 0;
    const legendH = items.length ? rows.length * lineH + pad : 0;
    const out = document.createElement("canvas");
    out.width = canvas.width;
    out.height = Math.ceil(titleH + canvas.height + legendH + pad);
    const ctx = out.getContext("2d");
    ctx.fillStyle = background(root);
    ctx.fillRect(0, 0, out.width, out.height);
    const ink = getComputedStyle(root).color || "#222";
    if (title) {
      ctx.fillStyle = ink;
      ctx.font = font(13, true);
      ctx.textAlign = "center";
      ctx.textBaseline = "middle";
      titleLines.forEach((line, i) =>
        ctx.fillText(line, out.width / 2, (i + 0.5) * titleLineH + 2 * k));
    }
    ctx.drawImage(canvas, 0, titleH);
    ctx.font = font(12, false);
    ctx.textAlign = "left";
    ctx.textBaseline = "middle";
    rows.forEach((row, r) => {
      const y = titleH + canvas.height + pad + r * lineH + lineH / 2;
      for (const it of row) {
        ctx.strokeStyle = it.color;
        ctx.lineWidth = 2 * k;
        ctx.setLineDash(it.dashed ? [4 * k, 3 * k] : []);
        ctx.beginPath();
        ctx.moveTo(it.x, y);
        ctx.lineTo(it.x + 16 * k, y);
        ctx.stroke();
        ctx.fillStyle = ink;
        ctx.fillText(it.text, it.x + 22 * k, y);
      }
    });
    out.toBlob((blob) => {
      if (blob) download(blob, slug(title) + ".png");
      else console.error("dobtune: the PNG of", title, "could not be made");
    }, "image/png");
  }


  // ---- the loop's Bode: one x axis, cursor read-out, margin labels ---------------------------

  const LOOP_MAG = "|L| candidate";
  const LOOP_PHASE = "phase candidate";
  // Marker series label -> [short name, unit] (server/charts.py LOOP_*_CHART).
  const MARGIN_MARKS = {
    "gain margin (up)": ["GM", "dB"],
    "gain-reduction margin (down)": ["GM", "dB"],
    "phase margin": ["PM", "deg"],
  };

  function uplots() {
    const reg = (window.__viserTestpoints && window.__viserTestpoints.uplots) || {};
    return Object.values(reg).map((e) => e.chart).filter((u) => document.body.contains(u.root));
  }

  function seriesIndex(u, label) {
    return u.series.findIndex((s) => s.label === label);
  }

  function loopCharts() {
    const all = uplots();
    return {
      mag: all.find((u) => seriesIndex(u, LOOP_MAG) > 0),
      phase: all.find((u) => seriesIndex(u, LOOP_PHASE) > 0),
    };
  }

  const fmtHz = (f) => Number(f.toPrecision(3)).toString() + " Hz";
  const fmt1 = (v) => (v === null || v === undefined || !isFinite(v) ? "-" : v.toFixed(1));

  // The x index of frequency f in chart u (the two charts share their grid).
  function indexOf(u, f) {
    const xs = u.data[0];
    let lo = 0;
    let hi = xs.length - 1;
    while (lo < hi) {
      const mid = (lo + hi) >> 1;
      if (xs[mid] < f) lo = mid + 1;
      else hi = mid;
    }
    return lo;
  }

  function readout(u) {
    const i = u.cursor.idx;
    const box = document.querySelector(".dt-loop-readout");
    const { mag, phase } = loopCharts();
    if (i === null || i === undefined || !box || !mag || !phase) return;
    const f = u.data[0][i];
    const at = (chart, label) => {
      const s = seriesIndex(chart, label);
      return s > 0 ? chart.data[s][indexOf(chart, f)] : NaN;
    };
    box.textContent = `f ${fmtHz(f)} | |L| ${fmt1(at(mag, LOOP_MAG))} dB | phase ` +
      `${fmt1(at(phase, LOOP_PHASE))} deg | active: |L| ${fmt1(at(mag, "|L| active"))} dB, ` +
      `phase ${fmt1(at(phase, "phase active"))} deg`;
    box.dataset.freqHz = String(f);
  }

  // A usable range of a log frequency axis.
  const goodRange = (min, max) => isFinite(min) && isFinite(max) && min > 0 && max > min;

  // A zoom of one chart's frequency axis sets the other's. The other chart's answer (its own
  // setScale hook, in the commit uPlot runs as a microtask) goes no further: a range the two
  // charts do not both map onto itself (NaN, or a log range each snaps elsewhere) bounced
  // between them forever, one microtask each, and the page never ran a task again (frozen:
  // no timers, no websocket, no input).
  const answering = new WeakSet();
  function syncX(u, key) {
    if (key !== "x") return;
    if (answering.has(u)) {
      answering.delete(u);
      return;
    }
    const { mag, phase } = loopCharts();
    const other = u === mag ? phase : u === phase ? mag : null;
    if (!other) return;
    const { min, max } = u.scales.x;
    if (!goodRange(min, max)) return;
    if (other.scales.x.min === min && other.scales.x.max === max) return;
    answering.add(other);
    other.setScale("x", { min, max });
    // Queued after its commit, so it runs after it: a commit that changes nothing fires no
    // hook, and the mark must not swallow the next zoom.
    queueMicrotask(() => answering.delete(other));
  }

  function labelMargins(u) {
    const ctx = u.ctx;
    // uPlot's pixels per CSS pixel (a PNG export draws under a transform of its own).
    const k = ctx.canvas.width / ctx.getTransform().a / (u.width || ctx.canvas.width);
    const drawn = [];
    u.series.forEach((s, si) => {
      const mark = MARGIN_MARKS[s.label];
      if (!mark || !s.show) return;
      const col = u.data[si];
      let i = -1;
      for (let j = 0; j + 1 < col.length; j++) {
        if (isFinite(col[j]) && isFinite(col[j + 1])) {
          i = j;
          break;
        }
      }
      if (i < 0) return;
      const f = u.data[0][i];
      const value = col[i + 1] - col[i];
      // A gain margin named as the verdict names it, positive (issue 33): where |L| > 1 at the
      // -180 deg crossing, the gain may fall that much ("down"); where |L| < 1, rise ("up").
      const text = mark[1] !== "dB"
        ? `${mark[0]} ${value.toFixed(1)} ${mark[1]} at ${fmtHz(f)}`
        : value < 0
          ? `gain-reduction margin ${(-value).toFixed(1)} dB down at ${fmtHz(f)}`
          : `gain margin ${value.toFixed(1)} dB up at ${fmtHz(f)}`;
      const x = u.valToPos(f, "x", true);
      const y = u.valToPos((col[i] + col[i + 1]) / 2, s.scale, true);
      const { left, width } = u.bbox;
      if (x < left || x > left + width) return; // zoomed out of view
      ctx.save();
      ctx.font = `bold ${Math.round(11 * k)}px sans-serif`;
      ctx.textBaseline = "middle";
      const w = ctx.measureText(text).width;
      // Where the label covers no curve (the GM label over |L| hid it from 0.2 to 1.3 Hz): beside
      // the marker, right or left, at the marker's height or above or below it, the place whose
      // box holds the fewest curve points (and no label drawn before) wins; the nearest first.
      const { top, height } = u.bbox;
      let best = null;
      for (const dy of [0, -16, 16, -32, 32, -48, 48, -64, 64]) {
        for (const right of [true, false]) {
          const tx = right ? x + 6 * k : x - 6 * k;
          const box = { l: right ? tx - 2 * k : tx - w - 2 * k, r: right ? tx + w + 2 * k : tx + 2 * k,
                        t: y + dy * k - 8 * k, b: y + dy * k + 8 * k };
          if (box.l < left || box.r > left + width || box.t < top || box.b > top + height) continue;
          const hits = curvePoints(u, box) +
            1000 * drawn.filter((d) => d.box.l < box.r && box.l < d.box.r &&
                                       d.box.t < box.b && box.t < d.box.b).length;
          if (!best || hits < best.hits) best = { hits, right, tx, ty: y + dy * k, box };
          if (hits === 0) break;
        }
        if (best && best.hits === 0) break;
      }
      if (!best) {
        ctx.restore();
        return;
      }
      ctx.textAlign = best.right ? "left" : "right";
      ctx.fillStyle = "rgba(255,255,255,0.8)";
      ctx.fillRect(best.box.l, best.box.t, best.box.r - best.box.l, best.box.b - best.box.t);
      ctx.fillStyle = typeof s.stroke === "function" ? s.stroke(u, si) : s.stroke;
      ctx.fillText(text, best.tx, best.ty);
      ctx.restore();
      drawn.push({ text, x: x / k, y: best.ty / k, covers: best.hits % 1000,
                   box: best.box, css: { l: best.box.l / k, r: best.box.r / k,
                                         t: best.box.t / k, b: best.box.b / k } });
    });
    u.root.dataset.marginLabels = JSON.stringify(drawn.map(({ box, ...d }) => d));
  }

  // How many points of the chart's curves (margin markers included) lie in `box` (canvas
  // pixels), the points of a curve taken every half pixel along x (interpolated between its
  // data points, so a steep segment through the box counts too).
  function curvePoints(u, box) {
    const xs = u.data[0];
    let hits = 0;
    u.series.forEach((s, si) => {
      if (si === 0 || !s.show) return;
      const col = u.data[si];
      let px0 = null;
      let py0 = null;
      for (let j = 0; j < xs.length; j++) {
        const v = col[j];
        if (v == null || !isFinite(v)) {
          px0 = null;
          continue;
        }
        const px = u.valToPos(xs[j], "x", true);
        const py = u.valToPos(v, s.scale, true);
        if (px0 !== null && Math.max(px0, px) >= box.l && Math.min(px0, px) <= box.r) {
          const n = Math.max(1, Math.ceil(Math.hypot(px - px0, py - py0) * 2));
          for (let i = 1; i <= n; i++) {
            const qx = px0 + (px - px0) * i / n;
            const qy = py0 + (py - py0) * i / n;
            if (qx >= box.l && qx <= box.r && qy >= box.t && qy <= box.b) hits++;
          }
        }
        px0 = px;
        py0 = py;
      }
    });
    return hits;
  }

  function addHook(u, name, fn) {
    const list = u.hooks[name] || (u.hooks[name] = []);
    if (!list.includes(fn)) {
      list.push(fn);
      return true;
    }
    return false;
  }

  // A frequency chart's x range back to its data when it is not a finite positive range:
  // viser's keeper of the zoom (x bounds relative to the data's) left NaN on a chart that got
  // new data while its tab was hidden (seen: the loop phase chart at NaN..1 after an apply
  // with the live traces shown), and the chart drew nothing when its tab came back.
  function repairLogX() {
    for (const u of uplots()) {
      const sc = u.scales.x;
      if (!sc || sc.distr !== 3 || goodRange(sc.min, sc.max)) continue;
      const xs = u.data && u.data[0];
      if (!xs || xs.length < 2 || !goodRange(xs[0], xs[xs.length - 1])) continue;
      u.setScale("x", { min: xs[0], max: xs[xs.length - 1] });
    }
  }

  // A chart's axes recomputed at its new size. uPlot's redraw(rebuildPaths, recalcAxes) sets its
  // "recompute the axes" flag to recalcAxes: a redraw between setSize and uPlot's commit (a
  // microtask) cancels the recomputation setSize asked for. uplot-react does just that when a
  // resize and new data come in one React render (a tab shown while the live charts stream):
  // the chart drew at its new width with the axes of the old one, after width 0 no x ticks,
  // labels or grid at all, until its y range changed (up to ~15 s seen, on 1-2 of the 4 live
  // charts after most Live traces -> Bode -> Live traces). A resized chart's next redraws
  // recompute its axes, until the commit that applies the size (its "setSize" hook).
  const resized = new WeakSet();
  const wrapped = new WeakSet();
  const sizeApplied = (u) => resized.delete(u);
  function keepAxesOnResize(u) {
    if (wrapped.has(u)) return;
    wrapped.add(u);
    const setSize = u.setSize;
    const redraw = u.redraw;
    u.setSize = (size) => {
      resized.add(u);
      setSize(size);
    };
    u.redraw = (rebuildPaths, recalcAxes) => redraw(rebuildPaths, recalcAxes || resized.has(u));
    addHook(u, "setSize", sizeApplied);
  }

  // Axes with a valid range and room for ticks but none found, recomputed once per size: the
  // resizes before keepAxesOnResize wrapped the chart (it wraps charts at the next upkeep).
  // One redraw with no new scale fires no setScale hook (nothing for syncX to answer).
  const axesRepairedAt = new WeakMap();
  function repairAxes() {
    for (const u of uplots()) {
      keepAxesOnResize(u);
      const size = `${u.bbox.width}x${u.bbox.height}`;
      const missing = u.axes.some((a) => {
        const sc = u.scales[a.scale];
        const room = a.side % 2 ? u.bbox.height : u.bbox.width;
        return a.show && a._found && a._found[1] === 0 && room > 0 && sc &&
          isFinite(sc.min) && isFinite(sc.max) && sc.max > sc.min;
      });
      if (!missing) axesRepairedAt.delete(u);
      else if (axesRepairedAt.get(u) !== size) {
        axesRepairedAt.set(u, size);
        u.redraw(false, true);
      }
    }
  }

  function hookLoopCharts() {
    const { mag, phase } = loopCharts();
    for (const u of [mag, phase]) {
      if (!u) continue;
      addHook(u, "setCursor", readout);
      addHook(u, "setScale", syncX);
      if (addHook(u, "draw", labelMargins)) u.redraw();
    }
  }

  // ---- the view in the URL ------------------------------------------------------------------

  function parseView(hash) {
    const want = {};
    const p = new URLSearchParams(hash.replace(/^#/, ""));
    for (const [key] of GROUPS) if (p.get(key)) want[key] = p.get(key);
    return want;
  }

  const tabLabel = (t) => (t.getAttribute("title") || t.textContent || "").trim();

  // fragment key -> the tabs of that group (the dock's tab strips, the tab groups inside
  // them).
  function groups() {
    const out = {};
    for (const strip of document.querySelectorAll("[data-dock-strip], [role=tablist]")) {
      const tabs = [...strip.querySelectorAll("[role=tab]")];
      const labels = tabs.map(tabLabel);
      for (const [key, member] of GROUPS) {
        if (!(key in out) && labels.includes(member)) out[key] = tabs;
      }
    }
    return out;
  }

  // What the URL asks for (fragment key -> tab label), until each is seen selected. No
  // wall-clock window: under load a group's strip came a minute or more after the page's first
  // one, and a window from the page's load (or from its first strip) forgot the URL's tab
  // (the Bode tab then opened on Decide). An entry waits, with no clock running, while its
  // strip is not on screen or while it sits in a tab that is not shown (Nyquist of the Bode
  // tab while Live traces is shown); once its tab is on screen it is activated until seen
  // selected (and held so, below), given up only after TRY_N activations and TRY_MS (both: a
  // loaded page runs few ticks). A strip comes before all its tabs (under load "Live traces" came seconds after
  // "Bode"): a tab not there yet is waited for, never given up. A user's own pick in a group
  // ends that group's entry (the page never takes a tab back from the user). Entries never
  // drawn (a group this page does not have, a label no group has) cost nothing: the URL keeps
  // them until the user picks a tab there.
  let want = parseView(location.hash); // read now: viser rewrites the URL when it starts
  const TRY_MS = 30000;
  const TRY_N = 60;
  // Seen selected is not done at once: under load the dock went back to its first tab after
  // the URL's had been selected (plot=Bode, with the URL asking for Live traces). An entry is
  // held, and its tab selected again, until seen selected over HOLD_MS and HOLD_TICKS.
  const HOLD_MS = 60000;
  const HOLD_TICKS = 20;
  // fragment key -> { since, n, held, heldTicks }: since its tab was first seen, activations,
  // since when it has been seen selected (0: it is not) and in how many ticks.
  let tries = {};

  const selectedIn = (tabs) => (tabs || []).find((t) => t.getAttribute("aria-selected") === "true");
  const onScreen = (tabs) => !!tabs && tabs.some((t) => t.getClientRects().length > 0 &&
                                                      t.getBoundingClientRect().width > 0);

  function activate(tab) {
    if (tab.closest("[data-dock-strip]")) {
      // What a keyboard user does: Enter on the dock's tab activates it (the dock's tabs act
      // on pointer events: a click() does nothing).
      tab.dispatchEvent(new KeyboardEvent("keydown", { key: "Enter", bubbles: true,
                                                       cancelable: true }));
    } else tab.click();
  }

  // The tab shown in a group: the URL's while it is still to be selected, else the selected
  // one (undefined: not drawn).
  function shownIn(key, g) {
    if (key in want) return want[key];
    const sel = selectedIn(g[key]);
    return sel ? tabLabel(sel) : undefined;
  }

  function restore() {
    const g = groups();
    for (const [key, label] of Object.entries(want)) {
      const parent = PARENT[key];
      if (parent) {
        const shown = shownIn(parent[0], g);
        if (shown !== undefined && shown !== parent[1]) continue; // its tab is not shown
      }
      const tabs = g[key];
      if (!onScreen(tabs)) continue; // not drawn or hidden: no clock runs
      const tab = tabs.find((x) => tabLabel(x) === label);
      if (!tab) continue; // not drawn yet: no clock runs
      const t = tries[key] || (tries[key] = { since: Date.now(), n: 0, held: 0, heldTicks: 0 });
      let done = false;
      if (tab.getAttribute("aria-selected") === "true") {
        if (!t.held) t.held = Date.now();
        t.heldTicks++;
        done = Date.now() - t.held > HOLD_MS && t.heldTicks >= HOLD_TICKS;
      } else if (t.n >= TRY_N && Date.now() - t.since > TRY_MS) {
        console.warn("dobtune: the tab from the URL was not selected:", key, label);
        done = true;
      } else {
        t.held = 0;
        t.heldTicks = 0;
        t.n++;
        activate(tab);
      }
      if (done) {
        delete want[key];
        delete tries[key];
      }
    }
  }

  // A tab the user picks (a real pointer or key event, not the page's own Enter): the URL's
  // entry for that group is done with.
  function userPicked(e) {
    if (!e.isTrusted || !Object.keys(want).length) return;
    const tab = e.target && e.target.closest && e.target.closest("[role=tab]");
    if (!tab) return;
    for (const [key, tabs] of Object.entries(groups())) {
      if (tabs.includes(tab) && key in want) {
        delete want[key];
        delete tries[key];
      }
    }
  }
  document.addEventListener("pointerdown", userPicked, true);
  document.addEventListener("keydown", userPicked, true);

  function viewHash() {
    const g = groups();
    const now = new URLSearchParams(location.hash.replace(/^#/, ""));
    const p = new URLSearchParams();
    for (const [key] of GROUPS) {
      const sel = selectedIn(g[key]);
      // A tab from the URL still to be selected: the URL keeps asking for it (the strip shows
      // its default tab for a moment first).
      if (key in want) p.set(key, want[key]);
      else if (sel) p.set(key, tabLabel(sel));
      else if (now.get(key)) p.set(key, now.get(key)); // its tab is hidden, or not drawn yet
    }
    return p.toString();
  }

  function syncUrl() {
    const h = viewHash();
    if (!h || location.hash.replace(/^#/, "") === h) return;
    history.replaceState(history.state, "", location.pathname + location.search + "#" + h);
  }

  window.addEventListener("hashchange", () => {
    const w = parseView(location.hash);
    if (Object.keys(w).length) {
      want = w;
      tries = {};
    }
    schedule();
  });

  // ---- the sliders' number boxes --------------------------------------------------------------
  // The cut-off slider moves on a log scale: its own number box would show log10 of the
  // frequency, where a user thinks in Hz. The gains' sliders ("Cv Kp, drag", ...): their number
  // boxes clamped "-1" to the minimum, dropped the "e" of "1e1" and kept the old value for
  // "abc", all silently. The text field under each (server/panels/controls.py) is the value:
  // the box goes.

  const LOG_SLIDER_LABEL = "Q cut-off, log scale";
  const GAIN_SLIDER_END = ", drag"; // server/panels/controls.py SLIDER_SUFFIX
  function hideLogBoxes() {
    for (const lab of document.querySelectorAll("label")) {
      const text = (lab.textContent || "").trim();
      if (!text.startsWith(LOG_SLIDER_LABEL) && !text.endsWith(GAIN_SLIDER_END)) continue;
      const slider = lab.htmlFor ? document.getElementById(lab.htmlFor) : null;
      const row = slider && slider.parentElement;
      if (!row) continue;
      const inputs = Array.from(row.querySelectorAll("input")).filter(i => i.type !== "hidden");
      const box = inputs[inputs.length - 1];
      if (!box) continue;
      const wrap = box.closest(".mantine-NumberInput-root") || box;
      if (wrap.style.display !== "none") wrap.style.display = "none";
    }
  }

  // ---- labels that name their field ------------------------------------------------------------
  // viser's label says for=<the control's id>, but its text field does not carry that id (its
  // slider and number field do; Mantine gives the text field an id of its own): the label named
  // nothing (screen readers, get_by_label). The label of such a row names its one input.

  function linkLabels() {
    for (const lab of document.querySelectorAll("label[for]")) {
      const id = lab.htmlFor;
      if (!id || document.getElementById(id)) continue;
      const row = lab.closest(".mantine-Flex-root");
      const inputs = row ? [...row.querySelectorAll("input, textarea")].filter(
        (i) => i.type !== "hidden") : [];
      if (inputs.length !== 1) continue;
      if (inputs[0].id) lab.htmlFor = inputs[0].id;
      else inputs[0].id = id;
    }
  }

  // ---- what the page shows, to the dashboard ---------------------------------------------------
  // The live charts' data goes only to the pages that show the Live traces tab
  // (server/http_access.py VIEW_PATH): the page says so when that changes, and every
  // REPORT_EVERY_MS (a dashboard restarted meanwhile knows it again).

  const VIEW_PATH = "/__dobtune_view";
  const LIVE_TAB = "Live traces";
  const REPORT_EVERY_MS = 10000;
  const RETRY_MS = 2000;
  let reported = null; // [live shown, when] of the last report the dashboard took
  let reporting = false;
  let failedAt = 0; // when the last report failed (0: it did not)
  function reportView() {
    const sel = selectedIn(groups().plot);
    if (!sel || reporting || Date.now() - failedAt < RETRY_MS) return; // tabs not drawn yet
    const live = tabLabel(sel) === LIVE_TAB;
    if (reported && reported[0] === live && Date.now() - reported[1] < REPORT_EVERY_MS) return;
    reporting = true;
    const fail = (why) => {
      if (!failedAt) console.warn("dobtune: the view report failed:", why);
      failedAt = Date.now();
    };
    fetch(`${VIEW_PATH}?dt_page=${PAGE_ID}&live=${live ? 1 : 0}${TOKEN_PARAM}`,
          { credentials: "same-origin", cache: "no-store" })
      .then((r) => {
        if (!r.ok) return fail(`HTTP ${r.status}`);
        reported = [live, Date.now()];
        failedAt = 0;
      }, fail)
      .finally(() => {
        reporting = false;
      });
  }

  // ---- upkeep ----------------------------------------------------------------------------------

  let pending = false;
  function tick() {
    pending = false;
    try {
      addPngButtons();
      addNyquistButtons();
      hookLoopCharts();
      repairLogX();
      repairAxes();
      hideLogBoxes();
      linkLabels();
      if (Object.keys(want).length) restore();
      syncUrl();
      reportView();
    } catch (err) {
      console.error("dobtune page script:", err);
    }
  }
  function schedule() {
    if (pending) return;
    pending = true;
    setTimeout(tick, 150);
  }
  function start() {
    new MutationObserver(schedule).observe(document.body, {
      childList: true, subtree: true, attributes: true, attributeFilter: ["aria-selected"],
    });
    setInterval(schedule, 1000);
    schedule();
  }
  if (document.body) start();
  else document.addEventListener("DOMContentLoaded", start);
})();
