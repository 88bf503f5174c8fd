// Writes a small LeRobot-like parquet file with hyparquet-writer, an implementation independent
// of ours, and prints it as a C++ byte list: tests/io/parquet_fixture_hyparquet.inc, which
// ParquetReadsHyparquetFile checks. Regenerate with
//   npm install hyparquet-writer@0.17.0 && node scripts/gen_parquet_fixture.mjs > tests/io/parquet_fixture_hyparquet.inc
import { parquetWriteBuffer } from 'hyparquet-writer'
const n = 6
const buf = parquetWriteBuffer({
  columnData: [
    { name: 'timestamp', data: Float32Array.from({ length: n }, (_, i) => i * 0.05) },
    { name: 'frame_index', data: Array.from({ length: n }, (_, i) => BigInt(i)) },
    { name: 'task', data: Array.from({ length: n }, (_, i) => i < 4 ? 'pick up the cup' : 'wave') },
    { name: 'observation.state', data: Array.from({ length: n }, (_, i) => [i, -i, i * 0.5]) },
  ],
  schema: [
    { name: 'root', num_children: 4 },
    { name: 'timestamp', type: 'FLOAT', repetition_type: 'REQUIRED' },
    { name: 'frame_index', type: 'INT64', repetition_type: 'REQUIRED' },
    { name: 'task', type: 'BYTE_ARRAY', converted_type: 'UTF8', repetition_type: 'OPTIONAL' },
    { name: 'observation.state', repetition_type: 'OPTIONAL', num_children: 1, converted_type: 'LIST' },
    { name: 'list', repetition_type: 'REPEATED', num_children: 1 },
    { name: 'element', type: 'FLOAT', repetition_type: 'OPTIONAL' },
  ],
  kvMetadata: [{ key: 'huggingface', value: '{"info": {"features": {}}}' }],
})
const bytes = new Uint8Array(buf)
let out = `// ${bytes.length} bytes written by hyparquet-writer 0.17.0 (scripts/gen_parquet_fixture.mjs)\n`
for (let i = 0; i < bytes.length; i += 16) out += '    ' + Array.from(bytes.slice(i, i + 16), b => '0x' + b.toString(16).padStart(2, '0')).join(', ') + ',\n'
console.log(out)
