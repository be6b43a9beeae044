// The live dashboard: renders what the server pushes over /ws; it never sends anything back.
"use strict";

const $ = (id) => document.getElementById(id);
const CHARTS = ["reward", "sps", "episode_return", "collisions", "coverage", "entropy", "value_loss"];

function fmt(value, digits) {
  return value === null || value === undefined ? "–" : Number(value).toFixed(digits);
}

// The newest point of a chart (the series with the largest step), as text with 4 significant digits.
function latest(series) {
  let best = null;
  for (const points of Object.values(series || {})) {
    const last = points[points.length - 1];
    if (last && (best === null || last[0] >= best[0])) best = last;
  }
  return best === null ? "–" : String(Number(best[1].toPrecision(4)));
}

function render(msg) {
  const mode = $("mode");
  mode.textContent = msg.mode;
  mode.className = "mode " + msg.mode;
  $("actors").textContent = "Actors=" + (msg.actors === null ? "–" : msg.actors);
  $("sps").textContent = "SPS=" + fmt(msg.sps, 0);
  $("obs").textContent = "Obs=" + fmt(msg.obs_age_ms, 0) + " ms";
  $("step").textContent = "Step=" + msg.step;
  $("run").textContent = "Run=" + (msg.run_id || "–");
  const corpus = $("corpus");
  if (msg.corpus) {
    corpus.textContent = "Corpus=" + msg.corpus.ready + "/" + msg.corpus.planned + (msg.corpus.done ? " ready" : " building") +
      (msg.corpus.rejected ? ", " + msg.corpus.rejected + " scenes rejected" : "");
    corpus.className = "";
  } else {
    corpus.className = "hidden";
  }
  $("bad-frames").textContent = "Bad frames=" + msg.bad_frames;
  $("decode-errors").textContent = "Decode errors=" + msg.decode_errors;
  $("waiting").className = msg.mode === "WAITING" ? "overlay" : "overlay hidden";
  if (msg.frame && String(msg.frame.seq) !== $("heatmap").dataset.seq) naviDrawFrame($("heatmap"), msg.frame);
  for (const chart of CHARTS) {
    const series = (msg.charts || {})[chart];
    naviDrawChart($("chart-" + chart), series);
    $("last-" + chart).textContent = latest(series);
  }
  naviDrawTrail($("trail"), msg.plan, msg.trail, msg.pose);
  $("pose").textContent = msg.pose
    ? "Pose=" + fmt(msg.pose.x, 2) + "," + fmt(msg.pose.y, 2) + "," + fmt(msg.pose.z, 2)
    : "Pose=–";
  $("plan").textContent = msg.plan ? "Plan=" + msg.plan.scene + " @ z " + fmt(msg.plan.z, 2) + " m" : "Plan=–";
}

naviConnect("/ws", render, (up) => {
  $("link").textContent = up ? "live" : "disconnected";
  $("link").className = up ? "up" : "down";
});
