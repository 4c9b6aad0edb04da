// Moves 10 000 points through kinetri-server and prints per-step figures.
// Usage: node examples/brownian.js [host:port]
'use strict';

const {Client} = require('..');

async function main(target) {
  const client = new Client(target);
  const n = 10000;
  const xy = new Float64Array(2 * n).map(() => Math.random());
  const s = await client.createSession(xy);
  console.log(`created ${s.name} with ${s.pointCount} points`);
  const steps = await client.openSteps(s.name);
  for (let k = 0; k < 20; k++) {
    const d = new Float64Array(2 * n).map(() => (Math.random() - 0.5) * 0.002);
    const t0 = Date.now();
    const ack = await steps.moveBy(d);
    const nn = await client.nearestAll(s.name);
    const mean = nn.distances.reduce((a, b) => a + b, 0) / nn.distances.length;
    console.log(`step ${ack.step}: ${ack.stats.path}, mean NN distance ` +
                `${mean.toFixed(5)}, ${Date.now() - t0} ms`);
  }
  await steps.close();
  await client.deleteSession(s.name);
  client.close();
}

main(process.argv[2] || '127.0.0.1:50051').catch((e) => {
  console.error(e.message);
  process.exit(1);
});
