// supramodal view: draws what the node sends over Server-Sent Events (/events), with plain canvas.
// Read-only unless the page was opened with #token=... (printed on the node's terminal): then the
// mark buttons (while recording) and the replay's controls send POSTs carrying that token.
"use strict";
(function () {
  const SPAN = 120;            // windows kept per stream for the plots
  const COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
                  "#bcbd22", "#17becf", "#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#3182bd"];
  // How grave a driver event is comes with it (its "severity": alarm, warning or info), decided in one place,
  // node/runtime/events.py's SEVERITY; the page only colours by it. An event without one: a warning.
  const SEVERITIES = new Set(["alarm", "warning", "info"]);
  const FEATURE_LEFT = 40;     // px of the features canvas left of the bars (the feature's name)
  const token = new URLSearchParams(location.hash.slice(1)).get("token") || "";
  const streams = new Map();   // name -> {el, history: [msg], classes}
  let hello = null;
  const $ = (sel, root) => (root || document).querySelector(sel);

  function text(el, s) { if (el.textContent !== s) el.textContent = s; }
  function fmt(x, d) { return x === null || x === undefined ? "-" : Number(x).toFixed(d); }

  function streamPanel(name) {
    let s = streams.get(name);
    if (s) return s;
    const el = $("#stream-template").content.firstElementChild.cloneNode(true);
    el.dataset.stream = name;
    text($(".name", el), name);
    text($(".kind", el), name === "fused" ? "fused decisions" : "stream");
    text($(".span", el), String(SPAN));
    const list = $("#streams");
    if (name === "fused") list.appendChild(el);
    else list.insertBefore(el, $('[data-stream="fused"]', list));
    if (name === "fused") { $(".feat", el).hidden = true; $(".img", el).hidden = true; $(".pairing", el).hidden = false; }
    s = {el: el, history: [], classes: [], imgFeature: null};
    streams.set(name, s);
    return s;
  }

  // -- one window --
  function onWindow(m) {
    const s = streamPanel(m.stream);
    s.history.push(m);
    if (s.history.length > SPAN) s.history.shift();
    if (m.classes) s.classes = m.classes;
    const el = s.el;
    el.dataset.window = String(m.window);
    el.dataset.predicted = m.predicted === undefined ? "" : m.predicted;
    const dec = $(".decision", el);
    text(dec, m.predicted === undefined ? "(no model)" : m.predicted + (m.unknown ? " (" + m.unknown + ")" : ""));
    dec.classList.toggle("right", m.truth != null && m.truth === m.predicted);
    dec.classList.toggle("wrong", m.truth != null && m.predicted !== undefined && m.truth !== m.predicted);
    text($(".confidence", el), fmt(m.confidence, 3));
    text($(".truth", el), m.truth == null ? "-" : m.truth);
    const acc = m.accumulated;
    text($(".pooled", el), acc ? (acc.label == null ? "(no contact)" : acc.label + " " + fmt(acc.confidence, 3) +
         " over " + acc.windows + " windows" + (acc.decided ? " (decided)" : "")) : "-");
    text($(".window", el), m.window + " @ " + fmt(m.end, 2) + " s");
    const flags = (m.flags || []).concat(m.in_contact === false ? ["no contact"] : []);
    $(".flags", el).innerHTML = flags.map(f => "<span>" + f + "</span>").join("");
    if (m.senses) el.dataset.senses = m.senses.join(",");
    drawPosteriors(s);
    if (m.features) { drawFeatures(s, m.features); drawImage(s); }
    text($("#clock"), "t = " + fmt(m.end, 1) + " s");
  }

  function drawPosteriors(s) {
    const c = $(".posteriors", s.el), g = c.getContext("2d"), W = c.width, H = c.height;
    g.clearRect(0, 0, W, H);
    g.strokeStyle = "#eee"; g.beginPath();
    for (const y of [0.25, 0.5, 0.75]) { g.moveTo(0, H - y * H); g.lineTo(W, H - y * H); }
    g.stroke();
    const h = s.history.filter(m => m.posteriors);
    if (!h.length) { g.fillStyle = "#999"; g.fillText("no posteriors (no model)", 10, 20); return; }
    const dx = W / (SPAN - 1), x0 = W - (h.length - 1) * dx;
    const classes = s.classes;
    for (let k = 0; k < classes.length; k++) {
      g.strokeStyle = COLORS[k % COLORS.length]; g.lineWidth = 1.5; g.beginPath();
      h.forEach((m, i) => { const y = H - 2 - (H - 4) * (m.posteriors[k] || 0); i ? g.lineTo(x0 + i * dx, y) : g.moveTo(x0, y); });
      g.stroke();
    }
    h.forEach((m, i) => {   // a fused window of one sense (its partner late or lost): an orange tick on top
      if ((m.flags || []).includes("alone")) { g.fillStyle = "#f79009"; g.fillRect(x0 + i * dx - dx / 2, 0, Math.max(dx, 1), 4); }
    });
    h.forEach((m, i) => {   // truth along the bottom: green right, red wrong
      if (m.truth == null) return;
      g.fillStyle = m.truth === m.predicted ? "#16794c" : "#b42318";
      g.fillRect(x0 + i * dx - dx / 2, H - 3, Math.max(dx, 1), 3);
    });
    const legend = $(".legend", s.el);
    const want = classes.map((c, k) => '<span><i style="background:' + COLORS[k % COLORS.length] + '"></i>' + c + "</span>").join("");
    if (legend.dataset.classes !== classes.join(",")) { legend.innerHTML = want; legend.dataset.classes = classes.join(","); }
  }

  function drawFeatures(s, features) {
    const c = $(".features", s.el), g = c.getContext("2d"), W = c.width, H = c.height;
    g.clearRect(0, 0, W, H);
    const names = Object.keys(features), rowH = H / names.length;
    names.forEach((name, r) => {
      const v = features[name], n = v.length, max = Math.max(1e-12, ...v.map(x => Math.abs(x || 0)));
      const bw = (W - FEATURE_LEFT) / n;
      g.fillStyle = "#333"; g.fillText(name, 2, r * rowH + 12);
      g.fillStyle = COLORS[r % COLORS.length];
      v.forEach((x, i) => { const bh = (rowH - 4) * Math.abs(x || 0) / max; g.fillRect(FEATURE_LEFT + i * bw, (r + 1) * rowH - 2 - bh, Math.max(bw - 1, 1), bh); });
    });
    if (names.length) channelAxis(s, features[names[0]].length);
  }

  // The bank's channels as the view sink sends them in hello (names and centre frequencies, in channel
  // order: the order of every feature's values); numbered from 0 where it has none for this stream
  // (a replay's page), or where their count is not the bars'.
  function channelLabels(stream, n) {
    const c = hello && hello.channels && hello.channels[stream];
    if (!c || !c.names || c.names.length !== n) return {what: "index", labels: Array.from({length: n}, (_, i) => [String(i)])};
    const hz = f => f == null ? "" : f >= 1000 ? (f / 1000).toFixed(f >= 10000 ? 0 : 1) + "k" : String(Math.round(f));
    return {what: "name, centre frequency in Hz", labels: c.names.map((name, i) => [name, hz((c.centre_hz || [])[i])])};
  }

  // Under the bars, each labelled channel's name and centre frequency, as many as fit side by side
  // (every k-th channel when they would overlap); redone only when the channels or the width change.
  function channelAxis(s, n) {
    const c = $(".features", s.el), axis = $(".chaxis", s.el), width = c.clientWidth;
    if (!width) return;                                       // not laid out (hidden): the next window draws it
    const {what, labels} = channelLabels(s.el.dataset.stream, n);
    const key = n + "|" + width + "|" + labels.map(l => l.join(" ")).join(",");
    if (axis.dataset.key === key) return;
    axis.dataset.key = key;
    text($(".chwhat", s.el), what);
    axis.innerHTML = "";
    const spans = labels.map((l, i) => {
      const span = document.createElement("span");
      span.dataset.channel = String(i);
      l.forEach((part, k) => { if (k) span.appendChild(document.createElement("br")); span.appendChild(document.createTextNode(part)); });
      axis.appendChild(span);
      return span;
    });
    const scale = width / c.width, pitch = (c.width - FEATURE_LEFT) / n * scale;
    const widest = Math.max(1, ...spans.map(sp => sp.offsetWidth));
    const step = Math.max(1, Math.ceil((widest + 4) / pitch));
    spans.forEach((sp, i) => {
      if (i % step) { sp.remove(); return; }
      const centre = (FEATURE_LEFT + (i + 0.5) * (c.width - FEATURE_LEFT) / n) * scale;
      sp.style.left = Math.max(0, Math.min(width - sp.offsetWidth, centre - sp.offsetWidth / 2)) + "px";
    });
  }

  function drawImage(s) {
    const c = $(".energy", s.el), g = c.getContext("2d"), W = c.width, H = c.height;
    const h = s.history.filter(m => m.features);
    if (!h.length) return;
    const names = Object.keys(h[h.length - 1].features);
    const name = names.includes("A") ? "A" : names.includes("Af") ? "Af" : names[0];
    text($(".imgfeature", s.el), name);
    let max = 1e-12;
    for (const m of h) for (const x of (m.features[name] || [])) max = Math.max(max, Math.abs(x || 0));
    const n = h[h.length - 1].features[name].length, cw = W / SPAN, ch = H / n, x0 = W - h.length * cw;
    g.clearRect(0, 0, W, H);
    h.forEach((m, i) => {
      (m.features[name] || []).forEach((x, k) => {
        const v = Math.sqrt(Math.abs(x || 0) / max);          // a square root shows the quiet channels too
        g.fillStyle = "hsl(" + (240 - 240 * v) + ",80%," + (15 + 45 * v) + "%)";
        g.fillRect(x0 + i * cw, H - (k + 1) * ch, Math.ceil(cw), Math.ceil(ch));
      });
    });
  }

  // -- health, events, hello, summary --
  function onHealth(m) {
    const rows = Object.entries(m.streams || {}).map(([name, st]) => {
      const f = st.frames || {}, l = st.latency_ms || {};
      return "<tr data-stream='" + name + "'><td>" + name + "</td><td>" + st.windows + "</td><td>" + f.delivered +
        "</td><td" + (f.filled ? " class=bad" : "") + ">" + f.filled + "</td><td" + (f.dropped ? " class=bad" : "") + ">" +
        f.dropped + "</td><td>" + fmt(l.p50, 2) + "</td><td>" + fmt(l.p99, 2) + "</td></tr>";
    });
    if (m.fusion) {
      const l = m.fusion.latency_ms || {};
      rows.push("<tr data-stream='fused'><td>fused</td><td>" + m.fusion.windows + "</td><td colspan=3>" + m.fusion.paired +
        " paired, " + m.fusion.alone + " alone</td><td>" + fmt(l.p50, 2) + "</td><td>" + fmt(l.p99, 2) + "</td></tr>");
      const fs = streams.get("fused");
      if (fs) {
        const late = Object.entries(m.fusion.late || {}).map(([k, v]) => k + " " + v).join(", ") || "none";
        const drop = Object.entries(m.fusion.dropouts || {}).filter(([, v]) => v).map(([k, v]) => k + " " + v).join(", ");
        text($(".pairing", fs.el), "paired " + m.fusion.paired + " · alone " + m.fusion.alone + " · late " + late +
             (drop ? " · dropped out: " + drop : ""));
      }
    }
    $("#frames tbody").innerHTML = rows.join("");
    $("#clocks tbody").innerHTML = Object.entries(m.clocks || {}).map(([name, c]) => c ?
      "<tr><td>" + name + "</td><td>" + fmt(c.ppm, 1) + "</td><td>" + fmt(c.delay_ms, 2) + "</td><td>" +
      fmt(c.jitter_ms, 2) + "</td></tr>" : "").join("") || "<tr><td colspan=4 class=muted>no live clock (file time)</td></tr>";
    $("#sinks tbody").innerHTML = (m.sinks || []).map(q =>
      "<tr><td>" + q.sink + "</td><td>" + q.written + "</td><td" + (q.dropped_windows ? " class=bad" : "") + ">" +
      q.dropped_windows + "</td><td>" + q.dropped_events + "</td><td>" + q.errors + "</td></tr>").join("");
    text($("#pages"), m.replay ? "a replay: the recording's counts at its end" :
         (m.clients || 0) + " page(s) open; " + (m.client_dropped || 0) + " messages dropped by pages that did not keep up");
  }

  function onEvent(m) {
    const severity = SEVERITIES.has(m.severity) ? m.severity : "warning";
    const li = document.createElement("li");
    li.className = severity;
    li.dataset.severity = severity;
    // On the node's common time, as the windows' times are (the sink puts it there); the host's clock only
    // where the node has no common time to give (a view that is not in a running graph), and said so.
    const when = document.createElement("span");
    when.className = "when";
    when.textContent = m.common_time != null ? fmt(m.common_time, 2) + " s"
      : new Date(m.time * 1000).toLocaleTimeString([], {hour12: false}) + " (host clock)";
    li.append(when, " " + (m.source ? m.source + " " : "") + m.event + (m.count > 1 ? " x" + m.count : "") + ": " + m.message);
    const log = $("#eventlog");
    log.insertBefore(li, log.firstChild);
    while (log.children.length > 50) log.removeChild(log.lastChild);
    banner((m.source ? m.source + ": " : "") + m.message, "event-" + m.event, severity);
  }

  function banner(msg, cls, severity) {
    const b = document.createElement("div");
    b.className = "banner " + cls + " " + severity;
    b.dataset.kind = cls;
    b.dataset.severity = severity;
    b.textContent = msg;
    $("#banners").appendChild(b);
    while ($("#banners").children.length > 4) $("#banners").removeChild($("#banners").firstChild);
    setTimeout(() => b.remove(), 8000);
  }

  function onHello(m) {
    hello = m;
    const mode = $("#mode");
    text(mode, m.mode); mode.className = "pill live";
    // The panels in the node's order (its scene's streams, then the fusion), whatever order windows came in.
    for (const name of m.streams || []) $("#streams").appendChild(streamPanel(name).el);
    $("#controls").hidden = !(m.control && token);
    const marks = $("#marks");
    marks.hidden = !m.marks;
    const box = $("#markbuttons");
    if (box.dataset.labels !== (m.labels || []).join(",")) {
      box.dataset.labels = (m.labels || []).join(",");
      box.innerHTML = "";
      for (const label of m.labels || []) {
        const b = document.createElement("button");
        b.type = "button"; b.textContent = label; b.dataset.label = label; b.disabled = !token;
        box.appendChild(b);
      }
    }
    $("#markend").disabled = !token;
    if (m.marks && !token) text($("#markstatus"), "read-only: open the URL with #token=... (printed on the terminal) to mark");
  }

  function onMark(m) {
    for (const b of document.querySelectorAll("#markbuttons button")) b.classList.toggle("on", b.dataset.label === m.label);
    text($("#markstatus"), m.label ? "marking " + m.label + " since " + fmt(m.time, 2) + " s" : "no label since " + fmt(m.time, 2) + " s");
  }

  function onSummary() {
    const mode = $("#mode"); text(mode, (hello ? hello.mode : "run") + " ended"); mode.className = "pill ended";
    banner(hello && hello.mode === "replay" ? "the recording has ended (from the start: replays it)"
           : "the run has ended: the summary is on the terminal", "ended", "info");
  }

  function onReset() {
    for (const s of streams.values()) s.history = [];
    if (hello) onHello(hello);
    $("#eventlog").innerHTML = "";
  }

  // -- requests that change something: the token and the page's own origin --
  async function post(path, body) {
    const r = await fetch(path, {method: "POST", headers: {"Content-Type": "application/json", "X-Supramodal-Token": token},
                                 body: JSON.stringify(body)});
    if (!r.ok) text($("#markstatus"), "refused (" + r.status + "): " + (await r.text()));
    return r.ok ? r.json() : null;
  }
  document.addEventListener("click", ev => {
    const b = ev.target.closest("button");
    if (!b) return;
    if (b.id === "markend" || b.parentElement.id === "markbuttons") post("/mark", {label: b.dataset.label || null});
    if (b.id === "pause") post("/control", {paused: b.textContent === "pause"}).then(r => { if (r) text(b, r.paused ? "play" : "pause"); });
    if (b.id === "restart") post("/control", {restart: true});
  });
  $("#speed").addEventListener("change", ev => post("/control", {speed: Number(ev.target.value)}));

  // -- the stream --
  const handlers = {window: onWindow, event: onEvent, health: onHealth, hello: onHello, summary: onSummary,
                    mark: onMark, reset: onReset};
  let received = 0;
  function connect() {
    const es = new EventSource("events");
    es.onopen = () => { text($("#conn"), "connected"); $("#conn").className = "pill live"; };
    es.onerror = () => { text($("#conn"), "reconnecting"); $("#conn").className = "pill ended"; };
    es.onmessage = ev => {
      const m = JSON.parse(ev.data);
      received++;
      document.body.dataset.received = String(received);
      const f = handlers[m.type];
      if (f) f(m);
    };
  }
  fetch("state").then(r => r.json()).then(onHello).catch(() => {}).finally(connect);
})();
