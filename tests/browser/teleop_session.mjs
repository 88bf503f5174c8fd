// A scripted teleoperation session in a real headless browser, scored: `dojo serve` with no
// arguments (the reference set on fresh held-out DojoSim scenes), the page opened with ?record=1,
// each joint's keys held in turn (positive, then negative, 3 s each; between holds 2 s released,
// with the page's home key H half way, so every hold starts from the start pose),
// then `dojo serve-check` replays the recording in DojoSim and reads it with the keypoint probe.
// Prints one JSON line: the check's scores, the page's frames/s and key-to-frame latency.
//
//   node tests/browser/teleop_session.mjs [--model student|teacher] [--teacher-steps N]
//                                        [--hold SECONDS] [--rest SECONDS] [--idle SECONDS] [--video OUT.mp4]
// --idle: no key at all for that long instead (does the stream keep a resting arm?).
// Environment: DOJO_EXE (default build/dojo), CHROMIUM (default /usr/bin/chromium).
// A measurement, not a test: docs/benchmarks.md records its numbers with the machine.
import { execFileSync } from "node:child_process";
import { existsSync, mkdtempSync, readFileSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { startServer } from "./serve_process.mjs";

const args = process.argv.slice(2);
const option = (name, fallback) => (args.includes(name) ? args[args.indexOf(name) + 1] : fallback);
const holdSeconds = Number(option("--hold", 3)), restSeconds = Number(option("--rest", 2));
const video = option("--video", ""), model = option("--model", "student");
const idleSeconds = Number(option("--idle", 0));
const exe = process.env.DOJO_EXE || join(".", "build", "dojo");
const browserPath = process.env.CHROMIUM || "/usr/bin/chromium";
let server = null, base = null;
function fail(message) {
  if (server) server.kill("SIGKILL");
  console.error("FAIL: " + message);
  process.exit(1);
}
const { chromium } = await import("playwright-core").catch(() =>
  fail("playwright-core is missing: run `npm ci --prefix tests/browser` (scripts/setup.sh does)"));
if (!existsSync(exe)) fail(`no dojo binary at ${exe} (build first, or set DOJO_EXE)`);

const tmp = mkdtempSync(join(tmpdir(), "dojo-teleop-"));
const serveArgs = ["serve", "--port", "0", "--recordings", join(tmp, "recordings")];
if (args.includes("--teacher-steps")) serveArgs.push("--teacher-steps", option("--teacher-steps", "35"));
let serverLog;
({ server, base, log: serverLog } =
  await startServer(exe, serveArgs, { startSeconds: 120, loadSeconds: 120 }).catch((e) => fail(e.message)));

const browser = await chromium.launch({ executablePath: browserPath, args: ["--no-sandbox", "--disable-gpu"] })
  .catch((e) => fail("cannot start chromium: " + e.message));
const percentile = (xs, p) => {
  const s = [...xs].sort((a, b) => a - b);
  return s.length ? +s[Math.min(s.length - 1, Math.floor(p * s.length))].toFixed(1) : null;
};
try {
  const page = await browser.newPage();
  let framesReceived = 0;
  page.on("websocket", (ws) => ws.on("framereceived", (f) => { if (typeof f.payload !== "string") ++framesReceived; }));
  await page.goto(base + "/?record=1");
  await page.waitForFunction(() => window.dojo.capabilities && document.getElementById("model").options.length > 0);
  const caps = await page.evaluate(() => window.dojo.capabilities);
  if (!caps.models.some((m) => m.name === model)) fail(`the server hosts no model '${model}'`);
  await page.selectOption("#model", model);
  await page.click("#start");
  await page.waitForFunction(() => window.dojo.ready !== null, null, { timeout: 60000 });
  const mapping = await (await fetch(base + "/dojosim_robot.mapping.json")).json();
  await page.focus("#view");
  const t0 = Date.now();
  const held = [];
  if (idleSeconds > 0) await page.waitForTimeout(idleSeconds * 1000);
  for (const dim of idleSeconds > 0 ? [] : mapping.dims) {
    for (const key of [dim.keys[1], dim.keys[0]]) {  // positive, then negative, each from the start pose
      await page.keyboard.down(key);
      await page.waitForTimeout(holdSeconds * 1000);
      await page.keyboard.up(key);
      held.push(`${dim.name} ${key}`);
      await page.waitForTimeout(restSeconds * 500);
      await page.keyboard.press("KeyH");  // home
      await page.waitForTimeout(restSeconds * 500);
    }
  }
  const seconds = (Date.now() - t0) / 1000;
  await page.click("#record");  // stop: the recording is finished and moved into place
  await page.waitForFunction(() => window.dojo.recorded !== null, null, { timeout: 60000 });
  const shown = await page.evaluate(() => ({ recorded: window.dojo.recorded, keyLatencies: window.dojo.keyLatencies,
                                            frames: window.dojo.frames, errors: window.dojo.errors }));
  if (shown.errors.length) fail("the page reported errors: " + shown.errors.join("; "));
  const checkArgs = ["serve-check", shown.recorded, "--json"];
  if (video) checkArgs.push("--video", video);
  const check = JSON.parse(execFileSync(exe, checkArgs, { encoding: "utf8", stdio: ["ignore", "pipe", "inherit"] }));
  console.log(JSON.stringify({
    model: caps.models.find((m) => m.name === model), keys_held: held.length, hold_s: holdSeconds, rest_s: restSeconds, seconds,
    frames_received_per_s: +(framesReceived / seconds).toFixed(2), frames_drawn: shown.frames,
    key_to_frame_ms_p50: percentile(shown.keyLatencies, 0.5), key_to_frame_ms_p95: percentile(shown.keyLatencies, 0.95),
    key_presses_measured: shown.keyLatencies.length, check }));
} catch (e) {
  console.error(serverLog().split("\n").slice(-20).join("\n"));
  console.error("FAIL: " + (e.stack || String(e)));
  process.exitCode = 1;
} finally {
  await browser.close();
  server.kill("SIGTERM");
  await new Promise((r) => server.once("exit", r));
  rmSync(tmp, { recursive: true, force: true });
}
