// The live dashboard: renders what the server pushes over /ws; it never sends anything back.
"use strict";

const $ = (id) => document.getElementById(id);

function fmt(value, digits) {
  return value === null || value === undefined ? "–" : Number(value).toFixed(digits);
}

function render(msg) {
  const mode = $("mode");
  mode.textContent = msg.mode;
  mode.className = "mode " + msg.mode;
  $("actors").textContent = "Actors=" + (msg.actors === null ? "–" : msg.actors);
  $("sps").textContent = "SPS=" + fmt(msg.sps, 0);
  $("obs").textContent = "Obs=" + fmt(msg.obs_age_ms, 0) + " ms";
  $("step").textContent = "Step=" + msg.step;
  $("run").textContent = msg.run_id ? "run " + msg.run_id : "";
  $("rejected").textContent = "Rejected=" + msg.rejected;
  $("waiting").className = msg.mode === "WAITING" ? "overlay" : "overlay hidden";
  if (msg.frame && String(msg.frame.seq) !== $("heatmap").dataset.seq) naviDrawFrame($("heatmap"), msg.frame);
  naviDrawChart($("reward-chart"), msg.reward);
  naviDrawChart($("sps-chart"), msg.sps_history);
}

naviConnect("/ws", render, (up) => {
  $("link").textContent = up ? "live" : "disconnected";
  $("link").className = up ? "up" : "down";
});
