// rig serve: the run browser's filter and the live run view (server-sent events + uPlot).
"use strict";

const CSRF = document.querySelector('meta[name="rig-csrf"]').content;

function runRow(r) {
  const tr = document.createElement("tr");
  tr.dataset.run = r.run_id;
  const cells = [null, r.started, r.dut_serial || "-", r.procedure, r.operator || "-", r.status, r.verdict || "-"];
  cells.forEach((text, i) => {
    const td = tr.insertCell();
    if (i === 0) {
      const a = document.createElement("a"); a.href = `/runs/${encodeURIComponent(r.run_id)}`; a.textContent = r.run_id; td.appendChild(a);
    } else td.textContent = text;
  });
  tr.cells[5].className = `status-${r.status}`;
  tr.cells[5].title = r.reason || "";  // why a run is damaged, incomplete or aborted
  tr.cells[6].className = `verdict-${r.verdict || "none"}`;
  return tr;
}

function rigRunsPage() {
  const input = document.getElementById("filter");
  const body = document.querySelector("#runs tbody");
  const applyFilter = () => {
    const q = input.value.trim().toLowerCase();
    for (const tr of body.querySelectorAll("tr[data-run]")) tr.hidden = q !== "" && !tr.textContent.toLowerCase().includes(q);
  };
  input.addEventListener("input", applyFilter);
  let shown = JSON.stringify(Array.from(body.querySelectorAll("tr[data-run]")).map((tr) => tr.textContent));
  const refresh = async () => {  // new runs and status changes appear without a reload
    try {
      const runs = await (await fetch("/api/runs")).json();
      const rows = runs.map(runRow);
      const text = JSON.stringify(rows.map((tr) => tr.textContent));
      if (text !== shown && rows.length) { body.replaceChildren(...rows); shown = text; applyFilter(); }
    } catch (e) { /* the server went away: keep what is shown */ }
  };
  setInterval(refresh, 2000);
}

function fmt(v) { return v === undefined || v === null ? "" : Number(v).toFixed(2); }

function setRow(table, row, vec) {
  const cells = table.rows[row].cells;
  for (let i = 0; i < 3; i++) cells[i + 1].textContent = vec ? fmt(vec[i]) : "";
}

async function control(runId, body) {
  const res = await fetch(`/runs/${encodeURIComponent(runId)}/control`, {
    method: "POST",
    headers: { "content-type": "application/json", "x-rig-csrf": CSRF },
    body: JSON.stringify(body),
  });
  if (!res.ok) {  // a refusal is one line, as JSON from the route or as text from the guard
    const text = await res.text();
    let line = text;
    try { line = JSON.parse(text).error || text; } catch (e) { /* plain text */ }
    alert(line.trim() || res.statusText);
  }
}

function fieldPlot(el) {
  const colors = ["#d62728", "#2ca02c", "#1f77b4"];
  const series = [{ label: "t (s)" }];
  for (const [i, ax] of ["x", "y", "z"].entries()) {
    series.push({ label: `B${ax} cmd`, stroke: colors[i], dash: [6, 4], width: 1.5 });
    series.push({ label: `B${ax} meas`, stroke: colors[i], width: 1.5 });
  }
  const data = [[], [], [], [], [], [], []];
  const width = Math.max(el.clientWidth || 900, 400);
  const plot = new uPlot({ width, height: 320, series, scales: { x: { time: false } },
                           axes: [{ label: "run time (s)" }, { label: "uT" }] }, data, el);
  return { plot, data };
}

// The panels a running step may name in its live values (a live_sources callable returning
// {"panel": {"name": ..., ...}}, docs/web.md): the page draws the one named, never a kind by name.
const PANELS = {
  "sigma-targets": (p) => {  // each value (a 1-sigma) against its target
    const cal = document.getElementById("cal"); cal.hidden = false;
    const body = cal.tBodies[0]; body.innerHTML = "";
    for (const [k, v] of Object.entries(p.values || {})) {
      const t = (p.targets || {})[k];
      const f = (p.forecast || {})[k];
      const tr = body.insertRow(); tr.insertCell().textContent = k;
      tr.insertCell().textContent = Number(v).toPrecision(3);
      tr.insertCell().textContent = f === undefined ? "-" : Number(f).toPrecision(3);
      tr.insertCell().textContent = t === undefined ? "-" : `target ${t}`;
      tr.insertCell().textContent = t !== undefined && v <= t ? "met" : "";
    }
    const line = document.getElementById("cal-forecast");
    line.textContent = p.forecast_line || ""; line.hidden = !p.forecast_line;
  },
};

const MAX_POINTS = 2400;  // 20 min at two points a second

function rigRunPage(running) {
  if (!running) return;
  const live = document.getElementById("live");
  const runId = live.dataset.run;
  const now = document.getElementById("now");
  const fp = fieldPlot(document.getElementById("field-plot"));
  let promptId = null;
  let lastEvents = "";
  document.getElementById("pause").onclick = () => control(runId, { action: "pause" });
  document.getElementById("resume").onclick = () => control(runId, { action: "resume" });
  document.getElementById("abort").onclick = () => {
    if (confirm("Abort the run? Every output goes to its safe state.")) control(runId, { action: "abort" });
  };
  document.getElementById("prompt-yes").onclick = () => control(runId, { action: "answer", prompt: promptId, yes: true });
  document.getElementById("prompt-no").onclick = () => control(runId, { action: "answer", prompt: promptId, yes: false });

  document.addEventListener("visibilitychange", () => { if (!document.hidden) fp.plot.setData(fp.data); });
  const source = new EventSource(`/runs/${encodeURIComponent(runId)}/live`);
  source.onmessage = (msg) => {
    const s = JSON.parse(msg.data);
    live.dataset.updates = String(Number(live.dataset.updates || 0) + 1);
    setRow(now, 1, s.field_cmd_ut); setRow(now, 2, s.reference_ut); setRow(now, 3, s.dut_ut);
    setRow(now, 4, s.dut_corrected_ut); setRow(now, 5, s.coil_a);
    const loads = Object.entries(s.loads_cmd_a || {}).map(([k, v]) =>
      `${k}: ${fmt(v)} A commanded` + (s.loads_a && k in s.loads_a ? `, ${fmt(s.loads_a[k])} A measured` : ""));
    document.getElementById("loads").textContent = loads.length ? "Loads: " + loads.join("; ") : "";
    if (s.step) {
      document.getElementById("step-line").textContent =
        `step ${s.step.index + 1}/${s.steps.length}: ${s.step.name} (${s.step.elapsed_s.toFixed(0)} of ${s.step.duration_s.toFixed(0)} s)`;
      document.getElementById("progress").value = s.progress;
      document.getElementById("eta").textContent = `${(100 * s.progress).toFixed(0)} %, ETA ${Math.floor(s.eta_s / 60)}:${String(Math.floor(s.eta_s % 60)).padStart(2, "0")}`;
    }
    const tl = document.getElementById("timeline");
    if (tl.children.length !== s.steps.length) {
      tl.innerHTML = "";
      for (const st of s.steps) { const li = document.createElement("li"); li.textContent = `${st.name} (${st.duration_s.toFixed(0)} s)`; tl.appendChild(li); }
    }
    Array.from(tl.children).forEach((li, i) => { li.className = s.step ? (i < s.step.index ? "done" : i === s.step.index ? "current" : "") : ""; });
    document.getElementById("paused-flag").hidden = !s.paused;
    document.getElementById("pause-pending").hidden = s.paused || !s.pause_requested;
    const box = document.getElementById("prompt");
    if (s.prompt) { promptId = s.prompt.id; document.getElementById("prompt-text").textContent = s.prompt.text; box.hidden = false; }
    else { promptId = null; box.hidden = true; }
    if (s.panel && PANELS[s.panel.name]) PANELS[s.panel.name](s.panel);  // the running step's own
    if (s.field_cmd_ut && s.reference_ut) {
      const d = fp.data;
      d[0].push(s.t);
      for (let i = 0; i < 3; i++) { d[1 + 2 * i].push(s.field_cmd_ut[i]); d[2 + 2 * i].push(s.reference_ut[i]); }
      if (d[0].length > MAX_POINTS) for (const col of d) col.shift();
      if (!document.hidden) fp.plot.setData(d);  // a tab in the background draws when shown
      live.dataset.points = String(d[0].length);
    }
    const events = s.events || [];
    const evKey = events.length ? `${events.length}:${events[events.length - 1].t}` : "";
    if (evKey !== lastEvents) {  // rebuilt only when there is something new
      lastEvents = evKey;
      const ev = document.getElementById("events"); ev.innerHTML = "";
      for (const e of events.slice().reverse()) {
        const li = document.createElement("li"); li.className = `level-${e.level}`;
        li.textContent = `${e.t.toFixed(1)} s [${e.level}] ${e.message}`; ev.appendChild(li);
      }
    }
    if (s.status && s.status !== "running") {
      source.close();
      const st = document.getElementById("status"); st.textContent = s.status; st.className = `status-${s.status}`;
      box.hidden = true;
      document.querySelector("#live .controls").hidden = true;  // nothing left to operate
      live.dataset.finished = s.status;
      const reason = document.createElement("p"); reason.id = "final-reason"; reason.textContent = `Run ended: ${s.status} (${s.reason}). Reload for the report.`;
      live.prepend(reason);
    }
  };
}

// The page says which view it is (no inline script: the Content-Security-Policy allows none).
if (document.body.dataset.page === "runs") rigRunsPage();
else if (document.body.dataset.page === "run") rigRunPage(document.body.dataset.running === "true");
