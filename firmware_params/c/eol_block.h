/* eol_block.h: parameter block check and CRC-32 (firmware contract section 2), C99.
 *
 * The bank image is an array of 16-bit words as the C28x flash holds it (low byte first).
 * No heap, no double, one 256-entry CRC table in ROM.
 */
#ifndef EOL_BLOCK_H
#define EOL_BLOCK_H

#include <stdint.h>

#include "eol_param_block.h"

#ifdef __cplusplus
extern "C" {
#endif

/* CRC-32/ISO-HDLC (zlib/PNG): reflected polynomial 0xEDB88320, init and final XOR 0xFFFFFFFF.
 * Start with crc = EOL_CRC32_INIT, feed bytes, finish with eol_crc32_final. */
#define EOL_CRC32_INIT 0xFFFFFFFFu
uint32_t eol_crc32_byte(uint32_t crc, uint16_t byte);
static inline uint32_t eol_crc32_final(uint32_t crc) { return crc ^ 0xFFFFFFFFu; }

/* CRC-32 of the first nbytes bytes of the word image w (low byte of each word first). */
uint32_t eol_crc32_words(const uint16_t *w, uint32_t nbytes);

/* Validate the block at the start of a bank image of avail_bytes bytes (EOL_PB_BANK_BYTES for a
 * flash bank). Returns EOL_PB_STATUS_VALID, EOL_PB_STATUS_CRC_MISMATCH or
 * EOL_PB_STATUS_HEADER_INVALID. Header rules first (magic, layout version 1 or 2, table_len a power
 * of two in 16..1024, block_bytes == 104 + 8*table_len (layout 1) or 3248 + 8*table_len (layout 2),
 * sequence not 0 nor 0xFFFFFFFF, the block inside avail_bytes), then the CRC at the end of the
 * block. Bytes after the block are ignored. */
uint16_t eol_block_check(const uint16_t *w, uint32_t avail_bytes);

#ifdef __cplusplus
}
#endif

#endif /* EOL_BLOCK_H */
