// Drive Debian's chromium (software GL) through puppeteer-core: open the omnisplat viewer page at
// the given poses, screenshot each view, and report what the page loaded. Used by test_viewer.py.
//
//   node tests/service/viewer_browser.mjs '{"base_url": "http://127.0.0.1:PORT", "scene_id": "...",
//     "poses": [{"name": "yaw0", "c2w": [16 numbers]}], "width": 640, "height": 480, "fov_deg": 90,
//     "out_dir": "OUT_DIR", "chromium": "/usr/bin/chromium", "timeout_s": 120,
//     "reload": false, "format": "ply" (or "spz": the page's ?format=),
//     "scene_gone": false (true: the scene's files answer the service's 404, as for a scene deleted after its
//     page was served; each view then reports "panel_visible"),
//     "page_shot": {"path": "page.png", "width": 960, "height": 600, "query": "c2w=..."}}'
//
// Prints one JSON object: {"views": [{"name", "screenshot", "splat_count", "load_seconds", "error"}],
// "console_errors": [...], "page_errors": [...], "external_requests": [...], "failed_requests": [...]}.
import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';
import puppeteer from 'puppeteer-core';

const args = JSON.parse(process.argv[2]);
const width = args.width || 640;
const height = args.height || 480;
const userDataDir = fs.mkdtempSync(path.join(os.tmpdir(), 'omnisplat-chromium-'));
const report = { views: [], console_errors: [], page_errors: [], external_requests: [], failed_requests: [] };

const browser = await puppeteer.launch({
  executablePath: args.chromium || '/usr/bin/chromium',
  headless: true,
  userDataDir,
  protocolTimeout: (args.timeout_s || 120) * 1000,
  args: [
    '--headless', '--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
    '--ignore-gpu-blocklist', '--disable-background-networking', '--disable-component-update',
    '--disable-sync', '--no-first-run', `--user-data-dir=${userDataDir}`,
  ],
});
function watch(page, label) {
  page.on('console', (msg) => {
    if (msg.type() === 'error') report.console_errors.push(`${label()}: ${msg.text()}`);
  });
  page.on('pageerror', (err) => report.page_errors.push(`${label()}: ${err.message}`));
  page.on('request', (req) => {
    const url = new URL(req.url());
    if (!['data:', 'blob:', 'about:'].includes(url.protocol) && url.hostname !== '127.0.0.1') {
      report.external_requests.push(req.url());
    }
  });
  page.on('requestfailed', (req) => report.failed_requests.push(`${req.url()}: ${req.failure()?.errorText}`));
  page.on('response', (res) => {
    if (res.status() >= 400) report.failed_requests.push(`${res.url()}: HTTP ${res.status()}`);
  });
}

const timeoutMs = (args.timeout_s || 120) * 1000;
try {
  // The first pose comes from the page's query string; the others move the loaded viewer's camera
  // (window.setCameraC2w) instead of loading the PLY again, unless "reload" is set.
  let page = null;
  let current = '';
  for (const [index, pose] of args.poses.entries()) {
    current = pose.name;
    const view = { name: pose.name, url: null, screenshot: null, splat_count: null, load_seconds: null,
                   error: null, via: null };
    const t0 = Date.now();
    try {
      if (page === null || args.reload) {
        if (page !== null) await page.close();
        page = await browser.newPage();
        await page.setViewport({ width, height, deviceScaleFactor: 1 });
        watch(page, () => current);
        if (args.scene_gone) {
          await page.setRequestInterception(true);
          page.on('request', (req) => (/\/gaussians\.(ply|spz)$/.test(new URL(req.url()).pathname)
            ? req.respond({ status: 404, contentType: 'application/json',
              body: JSON.stringify({ error: { code: 'scene_not_found', message: 'no scene with that id' } }) })
            : req.continue()));
        }
        const q = new URLSearchParams({
          c2w: pose.c2w.join(','), fov_deg: String(args.fov_deg || 90),
          width: String(width), height: String(height), bare: '1',
        });
        if (args.format) q.set('format', args.format);
        view.url = `${args.base_url}/v1/scenes/${args.scene_id}/viewer?${q}`;
        view.via = 'query';
        await page.goto(view.url, { waitUntil: 'load' });
        view.cross_origin_isolated = await page.evaluate(() => window.crossOriginIsolated);
        await page.waitForFunction('window.viewerReady === true || (window.viewerInfo && window.viewerInfo.error)',
          { timeout: timeoutMs, polling: 200 });
      } else {
        view.via = 'setCameraC2w';
        await page.evaluate((c2w) => window.setCameraC2w(c2w), pose.c2w);
      }
      const info = await page.evaluate(() => window.viewerInfo);
      view.splat_count = info.splatCount;
      view.load_seconds = info.loadSeconds;
      view.download_percent = info.downloadPercent;
      view.error = info.error;
      view.panel_visible = await page.evaluate(() => document.getElementById('panel').offsetParent !== null);
      view.screenshot = path.join(args.out_dir, `viewer-${pose.name}.png`);
      await page.screenshot({ path: view.screenshot, clip: { x: 0, y: 0, width, height } });
    } catch (err) {
      view.error = String(err && err.message ? err.message : err);
    }
    view.seconds = (Date.now() - t0) / 1000;
    report.views.push(view);
  }
  if (page !== null) await page.close();
  if (args.page_shot) {
    // the page as a user sees it, with its panel: no query = reference A's pose
    current = 'page_shot';
    page = await browser.newPage();
    await page.setViewport({ width: args.page_shot.width, height: args.page_shot.height, deviceScaleFactor: 1 });
    watch(page, () => current);
    const query = args.page_shot.query ? `?${args.page_shot.query}` : '';
    await page.goto(`${args.base_url}/v1/scenes/${args.scene_id}/viewer${query}`, { waitUntil: 'load' });
    await page.waitForFunction('window.viewerReady === true || (window.viewerInfo && window.viewerInfo.error)',
      { timeout: timeoutMs, polling: 200 });
    report.page_shot = { path: args.page_shot.path, info: await page.evaluate(() => window.viewerInfo) };
    await page.screenshot({ path: args.page_shot.path });
    await page.close();
  }
} finally {
  await browser.close();
  fs.rmSync(userDataDir, { recursive: true, force: true });
}
process.stdout.write(JSON.stringify(report) + '\n');
